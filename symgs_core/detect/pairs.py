"""Candidate pairs for voting: small clusters enumerated, large ones sampled, pairs that cannot be twins dropped."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..scene import GaussianScene
from .clusters import Clusters


def _ranges(starts: Tensor, lengths: Tensor) -> Tensor:
    """Concatenation of arange(s, s + l) for each (s, l) [K]; [sum l]."""
    total = int(lengths.sum())
    if total == 0:
        return torch.zeros(0, dtype=torch.long, device=starts.device)
    seg_start = torch.cumsum(lengths, 0) - lengths
    within = torch.arange(total, device=starts.device) - torch.repeat_interleave(seg_start, lengths, output_size=total)
    return torch.repeat_interleave(starts, lengths, output_size=total) + within


def enumerate_pairs(starts: Tensor, sizes: Tensor) -> tuple[Tensor, Tensor]:
    """Every unordered pair (a < b) of positions inside each cluster [K]; two index tensors [P]."""
    members = _ranges(starts, sizes)  # positions, cluster after cluster
    rank = members - torch.repeat_interleave(starts, sizes, output_size=members.numel())
    partners = torch.repeat_interleave(sizes, sizes, output_size=members.numel()) - 1 - rank
    a = torch.repeat_interleave(members, partners)
    b = _ranges(members + 1, partners)
    return a, b


def sample_pairs(starts: Tensor, sizes: Tensor, count: int, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """``count`` ordered pairs (a != b) of positions drawn uniformly from all pairs inside the clusters [K].

    A cluster is drawn with probability proportional to n_k (n_k - 1), then two distinct members uniformly.
    """
    device = starts.device
    weight = (sizes * (sizes - 1)).to(torch.float64)
    cdf = torch.cumsum(weight, 0)
    u = torch.rand(count, generator=gen, device=device, dtype=torch.float64) * cdf[-1]
    k = torch.searchsorted(cdf, u, right=True).clamp_max(sizes.numel() - 1)
    n = sizes[k]
    ra = (torch.rand(count, generator=gen, device=device) * n).long().clamp_max(n - 1)
    rb = (torch.rand(count, generator=gen, device=device) * (n - 1)).long().clamp_max(n - 2)
    rb = rb + (rb >= ra).long()
    return starts[k] + ra, starts[k] + rb


def candidate_pairs(
    clusters: Clusters, budget: int, enumerate_share: float, gen: torch.Generator
) -> tuple[Tensor, Tensor, int, int]:
    """Pairs of Gaussian indices [P] from the same cluster, at most about ``budget`` of them.

    All pairs when they fit in the budget. Otherwise clusters are enumerated from the smallest up while their pairs
    fit in ``enumerate_share`` of the budget, and the rest of the budget is sampled from the larger ones.
    Returns (i, j, enumerated, sampled).
    """
    sizes, starts = clusters.sizes, clusters.starts
    multi = sizes >= 2
    sizes, starts = sizes[multi], starts[multi]
    if sizes.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=clusters.order.device)
        return empty, empty, 0, 0
    pairs_per = sizes * (sizes - 1) // 2
    total = int(pairs_per.sum())
    if total <= budget:
        a, b = enumerate_pairs(starts, sizes)
        return clusters.order[a], clusters.order[b], total, 0
    by_size = torch.argsort(sizes)
    fits = torch.cumsum(pairs_per[by_size], 0) <= int(enumerate_share * budget)
    small, large = by_size[fits], by_size[~fits]
    a, b = enumerate_pairs(starts[small], sizes[small])
    enumerated = a.numel()
    sa, sb = sample_pairs(starts[large], sizes[large], budget - enumerated, gen)
    order = clusters.order
    return order[torch.cat([a, sa])], order[torch.cat([b, sb])], enumerated, sa.numel()


@dataclass(frozen=True)
class Axes:
    """Each Gaussian's most distinct principal axis."""

    u: Tensor  # [N, 3] unit
    round: Tensor  # [N] 1.0 where no axis stands out (the Gaussian pairs with any), else 0.0
    flat: Tensor  # [N] bool: the distinct axis is the shortest, so u is a surface normal


def distinct_axes(scene: GaussianScene, min_ratio: float) -> Axes:
    """Each Gaussian's most distinct principal axis.

    A flat Gaussian's distinct axis is its shortest (the surface normal), a needle's its longest. A mirror maps the
    axes of a Gaussian to the axes of its twin, so this one axis carries most of what the covariances can say about a
    pair. A Gaussian none of whose axes stands out by a factor ``min_ratio`` in scale is round: it pairs with any.
    """
    s, idx = scene.scales.sort(dim=1)
    gap_small = s[:, 1] - s[:, 0]  # log-ratio of the middle to the shortest scale
    gap_large = s[:, 2] - s[:, 1]
    axis = torch.where(gap_small >= gap_large, idx[:, 0], idx[:, 2])
    w, x, y, z = scene.normalized_quats().unbind(-1)
    # Column k of the rotation matrix is the direction of scale axis k.
    col0 = torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)], dim=-1)
    col1 = torch.stack([2 * (x * y - w * z), 1 - 2 * (x * x + z * z), 2 * (y * z + w * x)], dim=-1)
    col2 = torch.stack([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)], dim=-1)
    k = axis[:, None]
    u = torch.where(k == 0, col0, torch.where(k == 1, col1, col2))
    is_round = torch.maximum(gap_small, gap_large) < math.log(min_ratio)
    return Axes(u, is_round.to(u.dtype), (gap_small >= gap_large) & ~is_round)


def axes_agree(
    diff: Tensor, length2: Tensor, u_i: Tensor, u_j: Tensor, round_i: Tensor, round_j: Tensor, min_cos: float
) -> Tensor:
    """Mask [P]: the reflection of axis u_i [P, 3] across the pair's bisecting plane is within the angle of
    ``min_cos`` of u_j [P, 3] (either sign), or either Gaussian is round (``round_*`` [P], 0/1).

    The plane's normal is diff / |diff| (diff [P, 3], length2 [P] = |diff|^2), so
    H u_i . u_j = u_i . u_j - 2 (diff . u_i)(diff . u_j) / |diff|^2.
    """
    dot = lambda a, b: torch.einsum("ij,ij->i", a, b)  # noqa: E731
    cos = dot(u_i, u_j) - 2.0 * dot(diff, u_i) * dot(diff, u_j) / length2
    return cos.abs() + round_i + round_j >= min_cos
