"""Candidate pairs for voting: small clusters enumerated, large ones sampled, pairs that cannot be twins dropped."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from numba import prange
from torch import Tensor

from ..compiled import compiled, compiled_parallel
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


@compiled_parallel
def _sample_kernel(order, starts, sizes, cdf, u, ra, rb, i, j):  # noqa: ANN001, ANN202
    """``sample_pairs`` of the clusters (starts [K], sizes [K], cdf [K] of n (n - 1)) from its random numbers
    (u [S] float64 scaled to the cdf's total, ra [S] and rb [S] float32 in [0, 1)), as indices through order [N]
    into i [S] and j [S]. The member ranks are float32 products truncated, as torch computed them before."""
    last = starts.shape[0] - 1
    for r in prange(u.shape[0]):
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
    q = scene.normalized_quats()
    cpu = lambda t: t.detach().cpu().contiguous().numpy()  # noqa: E731
    n = len(scene)
    u = np.empty((n, 3), dtype=np.float32)
    is_round, flat = np.empty(n, dtype=np.float32), np.empty(n, dtype=np.bool_)
    _axes_kernel(cpu(s.float()), cpu(idx), cpu(q.float()), np.float32(math.log(min_ratio)), u, is_round, flat)
    device = scene.device
    return Axes(*(torch.from_numpy(t).to(device) for t in (u, is_round, flat)))


@compiled_parallel
def _axes_kernel(s, idx, q, log_ratio, u, round_, flat):  # noqa: ANN001, ANN202
    """``distinct_axes`` of sorted log-scales s [N, 3] (their axes idx [N, 3]) and unit quaternions q [N, 4] (wxyz)
    into u [N, 3], round_ [N] and flat [N]; in float32, operation for operation as torch computed it before."""
    one, two = np.float32(1.0), np.float32(2.0)
    for r in prange(s.shape[0]):
        gap_small = s[r, 1] - s[r, 0]  # log-ratio of the middle to the shortest scale
        gap_large = s[r, 2] - s[r, 1]
        axis = idx[r, 0] if gap_small >= gap_large else idx[r, 2]
        w, x, y, z = q[r, 0], q[r, 1], q[r, 2], q[r, 3]
        # Column ``axis`` of the rotation matrix: the direction of that scale axis.
        if axis == 0:
            u[r, 0], u[r, 1], u[r, 2] = one - two * (y * y + z * z), two * (x * y + w * z), two * (x * z - w * y)
        elif axis == 1:
            u[r, 0], u[r, 1], u[r, 2] = two * (x * y - w * z), one - two * (x * x + z * z), two * (y * z + w * x)
        else:
            u[r, 0], u[r, 1], u[r, 2] = two * (x * z + w * y), two * (y * z - w * x), one - two * (x * x + y * y)
        is_round = max(gap_small, gap_large) < log_ratio
        round_[r] = one if is_round else np.float32(0.0)
        flat[r] = gap_small >= gap_large and not is_round
