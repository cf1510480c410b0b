"""Candidate pairs for voting: small clusters enumerated, large ones sampled, pairs that cannot be twins dropped."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..scene import GaussianScene
from .clusters import Clusters
from .compiled import compiled


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
    positions = np.arange(int((starts + sizes).max()))
    a, b = np.empty(count, dtype=np.int64), np.empty(count, dtype=np.int64)
    _sample(positions, starts.cpu().numpy(), sizes.cpu().numpy(), count, gen, a, b)
    return torch.from_numpy(a).to(starts.device), torch.from_numpy(b).to(starts.device)


def _sample(
    order: np.ndarray,
    starts: np.ndarray,
    sizes: np.ndarray,
    count: int,
    gen: torch.Generator,
    i: np.ndarray,
    j: np.ndarray,
) -> None:
    """``sample_pairs`` as indices through order [N], into i [count] and j [count]."""
    cdf = np.cumsum((sizes * (sizes - 1)).astype(np.float64))
    u = torch.rand(count, generator=gen, device=gen.device, dtype=torch.float64) * float(cdf[-1])
    ra = torch.rand(count, generator=gen, device=gen.device)
    rb = torch.rand(count, generator=gen, device=gen.device)
    _sample_kernel(order, starts, sizes, cdf, u.cpu().numpy(), ra.cpu().numpy(), rb.cpu().numpy(), i, j)


def candidate_pairs(
    clusters: Clusters, budget: int, enumerate_share: float, gen: torch.Generator
) -> tuple[Tensor, Tensor, int, int]:
    """Pairs of Gaussian indices [P] from the same cluster, at most about ``budget`` of them.

    All pairs when they fit in the budget. Otherwise clusters are enumerated from the smallest up while their pairs
    fit in ``enumerate_share`` of the budget, and the rest of the budget is sampled from the larger ones (the pairs
    of ``enumerate_pairs`` and ``sample_pairs``, written in one compiled pass).
    Returns (i, j, enumerated, sampled).
    """
    device = clusters.order.device
    # Per cluster, in numpy: small arrays, where torch's threads cost more than the work.
    sizes, starts = clusters.sizes.cpu().numpy(), clusters.starts.cpu().numpy()
    multi = sizes >= 2
    sizes, starts = sizes[multi], starts[multi]
    pairs_per = sizes * (sizes - 1) // 2
    small = np.arange(sizes.size)
    large = small[:0]
    if int(pairs_per.sum()) > budget:
        by_size = torch.argsort(torch.from_numpy(sizes)).numpy()  # torch's order of equal sizes, as before
        fits = np.cumsum(pairs_per[by_size]) <= int(enumerate_share * budget)
        small, large = by_size[fits], by_size[~fits]
    enumerated = int(pairs_per[small].sum())
    sampled = budget - enumerated if large.size else 0
    i = np.empty(enumerated + sampled, dtype=np.int64)
    j = np.empty(enumerated + sampled, dtype=np.int64)
    order = clusters.order.cpu().numpy()
    _enumerate_kernel(order, starts[small], sizes[small], i, j)
    if sampled:
        _sample(order, starts[large], sizes[large], sampled, gen, i[enumerated:], j[enumerated:])
    return torch.from_numpy(i).to(device), torch.from_numpy(j).to(device), enumerated, sampled


@compiled
def _enumerate_kernel(order, starts, sizes, i, j):  # noqa: ANN001, ANN202
    """``enumerate_pairs`` of the clusters (starts [K], sizes [K]) as Gaussian indices (through order [N]) into the
    beginning of i and j."""
    r = 0
    for k in range(starts.shape[0]):
        s, n = starts[k], sizes[k]
        for a in range(s, s + n - 1):
            for b in range(a + 1, s + n):
                i[r], j[r] = order[a], order[b]
                r += 1


@compiled
def _sample_kernel(order, starts, sizes, cdf, u, ra, rb, i, j):  # noqa: ANN001, ANN202
    """``sample_pairs`` of the clusters (starts [K], sizes [K], cdf [K] of n (n - 1)) from its random numbers
    (u [S] float64 scaled to the cdf's total, ra [S] and rb [S] float32 in [0, 1)), as indices through order [N]
    into i [S] and j [S]. The member ranks are float32 products truncated, as torch computed them before."""
    last = starts.shape[0] - 1
    for r in range(u.shape[0]):
        k = min(np.searchsorted(cdf, u[r], side="right"), last)
        n = sizes[k]
        a = min(int(ra[r] * np.float32(n)), n - 1)
        b = min(int(rb[r] * np.float32(n - 1)), n - 2)
        if b >= a:
            b += 1
        i[r], j[r] = order[starts[k] + a], order[starts[k] + b]


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
