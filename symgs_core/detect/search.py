"""Mirror search, level by level: cluster, vote, find and refine the peak, then match the two sides."""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Sequence
from typing import cast

import torch
from torch import Tensor

from ..cameras import Focus
from ..devices import HOST
from ..mirror import Plane, canonical_sign
from ..scene import GaussianScene
from .clusters import Clusters, attributes, cluster
from .components import spatial_components
from .config import DetectConfig
from .frame import normalised_frame
from .grid import GridSpec, VoteIndex, top_peaks
from .membership import Matcher, Sides
from .pairs import Axes, candidate_pairs, distinct_axes
from .refine import refine_from_pairs
from .result import Mirror
from .votes import cast_votes

_MAX_OFFSET = 1.0  # planes farther than the robust radius from the centre cut off (almost) nothing
_REFINE_WINDOW = 5  # cells around the peak whose votes feed the refinement
_SUPPRESS_WINDOW = 4  # cells around a rejected peak cleared before the next candidate
_SAME_PLANE_CELLS = 4  # a candidate this many cells from a known mirror is that mirror again
_SPARE_PEAKS = 2  # peaks per candidate or known mirror: one plane may leave a peak or two
_CHANCE_PLANES = 6  # random planes that measure how much matches by chance
_MAX_PARTS = 8  # separate parts of a working set searched on their own, largest first
_SAME_ANGLE_DEG = 1.0  # a part's mirror this close to the whole set's is that mirror
# A part holding more than this share of the working set is most of it: its mirror is significant in the whole set's
# search already, and searching it again would double the time of a scene that is one object and scattered floaters.
_LARGEST_PART = 0.5
# The cameras' focus is searched on its own unless it holds nearly the whole working set (searched already): an object
# may fill more than half of what its photographs frame, and its surroundings still hold most of the Gaussians there.
_FOCUS_LEAVES = 0.1
_HOPELESS_SE = 4.0  # a candidate whose sampled matched share is this many standard errors below min_coverage ...


class _Clock:
    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self._t = time.perf_counter()

    def lap(self, step: str) -> None:
        now = time.perf_counter()
        self.seconds[step] += now - self._t
        self._t = now


def detect(
    scene: GaussianScene,
    config: DetectConfig | None = None,
    *,
    exclude: Sequence[Plane] = (),
    focus: Focus | None = None,
) -> list[Mirror]:
    """Mirrors of ``scene``, most dominant first, with the membership of each level's working set.

    Level 0 searches the whole scene; level l searches the left and out sets of level l - 1 (what the hierarchy
    keeps). Indices in every ``Mirror`` refer to ``scene``. Stops at ``max_mirrors``, when the working set is
    smaller than ``min_gaussians``, or when no candidate peak reaches ``min_coverage``. A plane found at one level,
    or listed in ``exclude`` (mirrors of earlier levels, when the caller runs one level at a time), is not reported
    again: the parts of the scene it failed to match would otherwise make it come back. ``focus``: what the cameras
    of the scene's photographs look at (``cameras.focus``), searched first and on its own: an object among its
    surroundings holds too small a share of a capture to be significant in the whole set. Non-finite Gaussians are
    never members. Indices come back on the scene's device.
    """
    if not isinstance(scene, GaussianScene):
        raise TypeError(f"detect takes a GaussianScene (load_scene reads one from a file), got {type(scene).__name__}")
    config = config or DetectConfig()
    known = list(exclude)
    # Detection runs on the CPU by design, whatever the scene's device: its passes are compiled CPU code (numba) and
    # scipy's KD-tree, and its many small steps ran 18x slower as GPU kernels. It reads no higher SH bands, so only the
    # first attributes travel here, once; the memberships travel back to the scene's device at the end.
    device = scene.device
    light = scene.with_(sh_rest=scene.sh_rest[:, :0]).detach().to(HOST)
    parts = (light.means, light.scales, light.sh_dc, light.opacities[:, None], light.quats)
    # A finite row sum has finite terms; a non-finite one may be finite terms that overflow: those rows are checked.
    finite = torch.isfinite(cast(Tensor, sum(t.sum(dim=1) for t in parts)))  # parts is not empty: a tensor
    suspect = torch.nonzero(~finite)[:, 0]
    if suspect.numel():
        finite[suspect] = torch.cat([torch.isfinite(t[suspect]) for t in parts], dim=1).all(dim=1)
    working = torch.nonzero(finite)[:, 0]
    mirrors: list[Mirror] = []
    for level in range(config.max_mirrors):
        if working.numel() < config.min_gaussians:
            break
        subset = light if working.numel() == len(light) else light.select(working)
        found, where = _detect_in_focus(subset, config, level, known, focus), "focus"
        if found is None:
            found, where = _best(_detect_level(subset, config, level, known),
                                 _detect_in_parts(subset, config, level, known))  # fmt: skip
        if found is None:
            break
        plane, votes, sides, timings = found
        is_out = torch.ones(working.numel(), dtype=torch.bool, device=working.device)
        is_out[sides.right] = False
        kept = working[is_out]  # left and out, in ascending order: the next working set
        is_out[sides.left] = False
        coverage = (sides.left.numel() + sides.right.numel()) / working.numel()
        left, right, out = (working[s].to(device) for s in (sides.left, sides.right, is_out))
        mirrors.append(Mirror(plane, votes, left, right, out, coverage, level, timings, where))
        known.append(plane)
        working = kept
    return mirrors


Found = tuple[Plane, int, Sides, dict[str, float]]


def _detect_in_parts(scene: GaussianScene, config: DetectConfig, level: int, known: list[Plane]) -> list[Found]:
    """The mirror of each spatially separate part that has one (``components``): a small object beside a large one
    covers too little of the whole working set to be significant there. Sides index ``scene``."""
    frame = normalised_frame(scene.means.float(), config.radius_quantile)
    if frame is None:
        return []
    parts = spatial_components(scene.means, frame.radius, min_size=config.min_gaussians)
    parts = [part for part in parts if part.numel() <= _LARGEST_PART * len(scene)][:_MAX_PARTS]
    return [f for f in (_detect_in(scene, part, config, level, known) for part in parts) if f is not None]


def _detect_in_focus(
    scene: GaussianScene, config: DetectConfig, level: int, known: list[Plane], focus: Focus | None
) -> Found | None:
    """The mirror of the Gaussians in ``focus``, unless it holds nearly all of ``scene`` (searched as a whole). It
    comes before the other mirrors of its level: the photographs are of it, while its surroundings (a table, a floor,
    a wall) may have symmetries of their own that match more Gaussians; those are sought at the next levels."""
    if focus is None:
        return None
    held = focus.holds(scene.means)
    if not config.min_gaussians <= held.numel() <= (1.0 - _FOCUS_LEAVES) * len(scene):
        return None
    return _detect_in(scene, held, config, level, known)


def _detect_in(
    scene: GaussianScene, part: Tensor, config: DetectConfig, level: int, known: list[Plane]
) -> Found | None:
    """The mirror of ``scene``'s Gaussians ``part`` [P], its sides indexing ``scene``."""
    found = _detect_level(scene.select(part), config, level, known)
    if found is None:
        return None
    plane, votes, sides, timings = found
    return plane, votes, Sides(part[sides.left], part[sides.right]), timings


def _best(whole: Found | None, parts: list[Found]) -> tuple[Found | None, str]:
    """Of the mirror found in the whole working set and those found in its separate parts, the one that matches the
    most Gaussians, and where it was found ("scene" or "part"): the larger first, whether a scene-wide mirror or a
    small object's own. A part's mirror that is the whole set's mirror again gives way to it (its membership spans
    every part)."""
    if whole is not None:
        parts = [p for p in parts if p[0].angle_deg(whole[0]) > _SAME_ANGLE_DEG]
    options = [(whole, "scene")] if whole is not None else []
    options += [(part, "part") for part in parts]
    if not options:
        return None, "scene"
    return max(options, key=lambda option: option[0][2].left.numel() + option[0][2].right.numel())


def _detect_level(
    scene: GaussianScene, config: DetectConfig, level: int, known: list[Plane]
) -> tuple[Plane, int, Sides, dict[str, float]] | None:
    clock = _Clock()
    frame = normalised_frame(scene.means.float(), config.radius_quantile)
    if frame is None:
        return None
    x = frame.to_local(scene.means.float())
    clock.lap("frame")
    attrs = attributes(scene)
    groups = cluster(attrs, config.colour_bins, config.opacity_bins, config.scale_bins)
    clock.lap("cluster")
    spec = GridSpec(config.angle_res, config.offset_res, _MAX_OFFSET)
    axes = distinct_axes(scene, config.axis_ratio)
    votes_cell, votes_i, votes_j = _vote(x, groups, axes, spec, config, level, clock)
    index = VoteIndex(votes_cell, spec)
    peaks = top_peaks(votes_cell, spec, _SPARE_PEAKS * (config.candidates + len(known)), _SUPPRESS_WINDOW, index)
    clock.lap("peak")
    n_points = x.shape[0]
    matcher: Matcher | None = None
    chance: float | None = None
    tried: list[tuple[Tensor, float]] = []
    for coord, peak_votes in peaks:
        if len(tried) == config.candidates or peak_votes < config.min_votes:
            break  # peaks come strongest first
        normal, offset = spec.plane(coord)
        near = index.near(coord, _REFINE_WINDOW)
        xi, xj = x[votes_i[near].long().to(x.device)], x[votes_j[near].long().to(x.device)]
        normal, offset = refine_from_pairs(
            xi, xj, normal, offset, config.angle_res, config.offset_res, config.refine_iters
        )
        normal, offset = _canonical(normal, offset)
        clock.lap("refine")
        if any(_same_plane(normal, offset, frame.plane_to_local(p), config) for p in known) or any(
            _same_plane(normal, offset, t, config) for t in tried
        ):
            continue  # a known mirror, or a peak that refines to a plane already tried
        tried.append((normal, offset))
        if matcher is None:
            matcher = Matcher(
                x, attrs, axes, tolerance=config.match_tolerance, attribute_weight=config.attribute_weight
            )
            clock.lap("membership")
        normal, offset = _canonical(*matcher.settle(normal, offset, config.icp_iters))
        clock.lap("refine")
        # ... is not matched in full: that costs as much as all the steps before, and most peaks of a level that has
        # no more mirrors match a few percent, which a sample of whole voxels tells for a few percent of the cost.
        share, error = matcher.sampled_share(normal, offset)
        if share + _HOPELESS_SE * error < config.min_coverage:
            clock.lap("membership")
            continue
        sides = matcher.sides(normal, offset)
        coverage = (sides.left.numel() + sides.right.numel()) / n_points
        if coverage >= config.min_coverage and chance is None:
            chance = matcher.chance_coverage(_CHANCE_PLANES, config.seed + level)
        # Whenever coverage reaches min_coverage, chance is measured just above.
        significant = coverage >= config.min_coverage and coverage >= config.min_significance * cast(float, chance)
        clock.lap("membership")
        if significant and sides.left.numel():
            world_n, world_g = frame.plane_to_world(normal.to(frame.centre.dtype).to(frame.centre.device), offset)
            return Plane.from_tensor(world_n, world_g), peak_votes, sides, dict(clock.seconds)
    return None


def _vote(
    x: Tensor,
    groups: Clusters,
    axes: Axes,
    spec: GridSpec,
    config: DetectConfig,
    level: int,
    clock: _Clock,
) -> tuple[Tensor, Tensor, Tensor]:
    """The votes of the candidate pairs: per vote, its flat cell [V] and its pair (i [V], j [V]), on the CPU."""
    device = x.device
    gen = torch.Generator(device=device).manual_seed(config.seed + level)
    budget = max(1, min(config.pair_budget, int(config.pairs_per_gaussian * x.shape[0])))
    pi, pj, _, _ = candidate_pairs(groups, budget, config.enumerate_share, gen)
    min_cos = None if config.axis_tolerance is None else math.cos(config.axis_tolerance)
    max_d2 = math.inf if config.max_pair_distance is None else config.max_pair_distance**2
    clock.lap("pairs")
    votes = cast_votes(x, axes, pi, pj, spec, min_cos, max_d2)
    clock.lap("vote")
    return votes


def _same_plane(normal: Tensor, offset: float, other: tuple[Tensor, float], config: DetectConfig) -> bool:
    """Whether two planes of the normalised frame are within a few accumulator cells of each other."""
    n2, g2 = other
    cos = float(normal.to(torch.float64) @ n2.to(torch.float64))
    sign = 1.0 if cos >= 0 else -1.0
    angle = math.acos(min(1.0, abs(cos)))
    return (
        angle <= _SAME_PLANE_CELLS * config.angle_res
        and abs(offset - sign * g2) <= _SAME_PLANE_CELLS * config.offset_res
    )


def _canonical(normal: Tensor, offset: float) -> tuple[Tensor, float]:
    """The same plane, written as ``Plane.canonical`` writes it (``mirror.canonical_sign``)."""
    return (normal, offset) if canonical_sign(normal.tolist()) > 0 else (-normal, -offset)
