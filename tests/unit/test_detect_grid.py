"""The accumulator's seam, its peaks, and the pair enumeration and sampling that feed it."""

from __future__ import annotations

import math

import torch

from symgs_core.detect.clusters import Clusters, rgb_to_hsv
from symgs_core.detect.grid import GridSpec, VoteIndex, top_peaks
from symgs_core.detect.pairs import Axes, candidate_pairs, enumerate_pairs, sample_pairs
from symgs_core.detect.votes import cast_votes
from symgs_core.mirror import reflect_points

SPEC = GridSpec(cell=0.01, depth=0.01, max_offset=1.0)


def _twin_votes(normal: torch.Tensor, offset: float, count: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Normals [P, 3] and offsets [P] voted by twin pairs across the plane (with float-rounding-sized noise), in
    random pair order."""
    g = torch.Generator().manual_seed(seed)
    a = torch.rand(count, 3, generator=g, dtype=torch.float64) - 0.5
    b = reflect_points(a, normal, offset) + 1e-9 * torch.randn(count, 3, generator=g, dtype=torch.float64)
    swap = torch.rand(count, generator=g) < 0.5  # which Gaussian of a pair comes first is arbitrary
    a, b = torch.where(swap[:, None], b, a), torch.where(swap[:, None], a, b)
    diff = a - b
    n = diff / diff.norm(dim=1, keepdim=True)
    return n.float(), ((n * (a + b)).sum(dim=1) / 2).float()


def test_plane_on_the_seam_collects_all_its_votes_in_one_cell() -> None:
    # n_z = 0: the normal lies on the rim of the canonical hemisphere, where n and -n meet.
    normal = torch.tensor([math.cos(0.7), math.sin(0.7), 0.0], dtype=torch.float64)
    n, g = _twin_votes(normal, 0.1, 500, seed=0)
    assert bool((n[:, 2] > 0).any() and (n[:, 2] < 0).any())  # votes arrive from both sides of the seam
    cells, source = SPEC.cells(n, g)
    counts = torch.bincount(cells)
    peak = int(counts.argmax())
    assert int(counts[peak]) == 500  # every pair voted into the peak cell, none split off
    assert set(source[cells == peak].tolist()) == set(range(500))
    coord = SPEC.unravel(torch.tensor([peak]))[0]
    plane_n, plane_g = SPEC.plane(coord)
    sign = 1.0 if float(plane_n @ normal) > 0 else -1.0
    assert math.degrees(math.acos(min(1.0, abs(float(plane_n @ normal))))) < 1.0
    assert abs(sign * plane_g - 0.1) <= SPEC.depth


def test_plane_away_from_the_seam_votes_once_per_pair() -> None:
    normal = torch.nn.functional.normalize(torch.tensor([0.3, -0.2, 0.9], dtype=torch.float64), dim=0)
    n, g = _twin_votes(normal, -0.2, 300, seed=1)
    cells, source = SPEC.cells(n, g)
    assert torch.equal(source, torch.arange(300))
    assert torch.unique(cells).numel() == 1


def test_peaks_dense_and_sparse_agree_and_suppress_the_seam_twin() -> None:
    normal = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    n1, g1 = _twin_votes(normal, 0.0, 400, seed=2)
    other = torch.nn.functional.normalize(torch.tensor([0.5, 0.1, 0.8], dtype=torch.float64), dim=0)
    n2, g2 = _twin_votes(other, 0.3, 150, seed=3)
    noise = torch.nn.functional.normalize(torch.randn(2000, 3, generator=torch.Generator().manual_seed(4)), dim=1)
    n = torch.cat([n1, n2, noise])
    g = torch.cat([g1, g2, torch.rand(2000, generator=torch.Generator().manual_seed(5)) - 0.5])
    cells, _ = SPEC.cells(n, g)
    sparse = top_peaks(cells, SPEC, 3, radius=4)
    dense = top_peaks(cells.repeat(300), SPEC, 3, radius=4)  # enough votes for the dense grid
    assert [v for _, v in sparse][:2] == [v // 300 for _, v in dense][:2]
    assert sparse[0][1] >= 400 and 150 <= sparse[1][1] < 400  # the seam twin of the first is not the second
    first_n, _ = SPEC.plane(sparse[0][0])
    second_n, _ = SPEC.plane(sparse[1][0])
    assert abs(float(first_n @ normal)) > 0.999 and abs(float(second_n @ other)) > 0.999


def test_enumerated_pairs_are_all_pairs_within_clusters() -> None:
    sizes = torch.tensor([1, 4, 2, 3])
    starts = torch.cumsum(sizes, 0) - sizes
    a, b = enumerate_pairs(starts, sizes)
    expected = set()
    for s, n in zip(starts.tolist(), sizes.tolist(), strict=True):
        expected |= {(s + i, s + j) for i in range(n) for j in range(i + 1, n)}
    assert set(zip(a.tolist(), b.tolist(), strict=True)) == expected
    assert a.numel() == len(expected)


def test_sampled_pairs_are_uniform_over_all_pairs() -> None:
    sizes = torch.tensor([2, 10, 40])
    starts = torch.cumsum(sizes, 0) - sizes
    gen = torch.Generator().manual_seed(0)
    a, b = sample_pairs(starts, sizes, 200_000, gen)
    assert bool((a != b).all())
    cluster_a = torch.searchsorted(starts, a, right=True) - 1
    assert torch.equal(cluster_a, torch.searchsorted(starts, b, right=True) - 1)
    share = torch.bincount(cluster_a, minlength=3).double() / a.numel()
    expected = (sizes * (sizes - 1)).double() / (sizes * (sizes - 1)).sum()
    assert torch.allclose(share, expected, atol=0.005)


def test_budget_enumerates_small_clusters_and_samples_large_ones() -> None:
    sizes = torch.tensor([3, 3, 1000])
    starts = torch.cumsum(sizes, 0) - sizes
    clusters = Clusters(order=torch.arange(int(sizes.sum())), starts=starts, sizes=sizes)
    i, j, enumerated, sampled = candidate_pairs(clusters, budget=10_000, enumerate_share=0.5, gen=torch.Generator())
    assert enumerated == 6 and sampled == 10_000 - 6 and i.numel() == 10_000
    small = (i < 6) & (j < 6)
    assert int(small.sum()) == 6
    i, j, enumerated, sampled = candidate_pairs(clusters, budget=10**6, enumerate_share=0.5, gen=torch.Generator())
    assert (enumerated, sampled) == (3 + 3 + 1000 * 999 // 2, 0)


def test_hsv_of_primaries_and_greys() -> None:
    rgb = torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [0.5, 0.5, 0.5], [0, 0, 0]])
    hsv = rgb_to_hsv(rgb)
    assert torch.allclose(hsv[:, 0], torch.tensor([0.0, 1 / 3, 2 / 3, 0.0, 0.0]))
    assert torch.allclose(hsv[:, 1], torch.tensor([1.0, 1.0, 1.0, 0.0, 0.0]))
    assert torch.allclose(hsv[:, 2], torch.tensor([1.0, 1.0, 1.0, 0.5, 0.0]))


def test_candidate_pairs_are_the_enumerated_then_the_sampled_pairs_through_the_order() -> None:
    sizes = torch.tensor([3, 1, 2, 50, 40])
    starts = torch.cumsum(sizes, 0) - sizes
    order = torch.randperm(int(sizes.sum()), generator=torch.Generator().manual_seed(0))
    clusters = Clusters(order=order, starts=starts, sizes=sizes)
    i, j, enumerated, sampled = candidate_pairs(clusters, 500, 0.5, torch.Generator().manual_seed(1))
    # Pairs per cluster, smallest first: 1 (size 2), 3, 780, 1225; a quarter of the budget fits the first two.
    assert (enumerated, sampled) == (4, 496)
    small, large = torch.tensor([2, 0]), torch.tensor([4, 3])
    a, b = enumerate_pairs(starts[small], sizes[small])
    sa, sb = sample_pairs(starts[large], sizes[large], 496, torch.Generator().manual_seed(1))
    assert torch.equal(i, order[torch.cat([a, sa])]) and torch.equal(j, order[torch.cat([b, sb])])


def test_cast_votes_are_the_cells_of_the_bisecting_planes_of_the_pairs_that_agree() -> None:
    g = torch.Generator().manual_seed(6)
    x = torch.rand(400, 3, generator=g) - 0.5
    x[1] = x[0]  # a coincident pair votes for nothing
    u = torch.nn.functional.normalize(torch.randn(400, 3, generator=g), dim=1)
    axes = Axes(u, (torch.rand(400, generator=g) < 0.3).float(), torch.zeros(400, dtype=torch.bool))
    i, j = torch.randint(400, (5000,), generator=g), torch.randint(400, (5000,), generator=g)
    i[0], j[0] = 0, 1
    min_cos = math.cos(0.5)
    cells, vi, vj = cast_votes(x, axes, i, j, SPEC, min_cos, math.inf)
    diff = (x[i] - x[j]).double()
    length2 = (diff * diff).sum(dim=1)
    ui, uj = u[i].double(), u[j].double()
    cos = (ui * uj).sum(dim=1) - 2.0 * (diff * ui).sum(dim=1) * (diff * uj).sum(dim=1) / length2
    keep = (length2 > 1e-12) & (cos.abs() + axes.round[i] + axes.round[j] >= min_cos)
    assert 1000 < int(keep.sum()) < 4000  # the pruning both keeps and drops
    normal = diff[keep] / length2[keep].sqrt()[:, None]
    offset = (normal * (x[i[keep]] + x[j[keep]]).double()).sum(dim=1) / 2
    expected, source = SPEC.cells(normal, offset)
    pair = lambda c, a, b: sorted(zip(c.tolist(), a.tolist(), b.tolist(), strict=True))  # noqa: E731
    assert pair(cells, vi, vj) == pair(expected, i[keep][source], j[keep][source])


def test_vote_index_finds_the_votes_near_a_cell_and_counts_blocks() -> None:
    g = torch.Generator().manual_seed(7)
    coords = torch.stack([torch.randint(0, s, (20_000,), generator=g) for s in SPEC.shape], dim=1)
    coords[:5000] = coords[:5000] % 9 + 100  # a dense corner
    _, sv, sg = SPEC.shape
    cells = ((coords[:, 0] * sv + coords[:, 1]) * sg + coords[:, 2]).int()
    index = VoteIndex(cells, SPEC)
    for centre, radius in ((torch.tensor([104, 103, 105]), 5), (torch.tensor([0, 200, 3]), 4)):
        brute = torch.nonzero((coords - centre).abs().amax(dim=1) <= radius)[:, 0]
        assert torch.equal(index.near(centre, radius), brute)
    blocks = coords // 2
    assert float(index.block_counts()[tuple(blocks[0])]) == float((blocks == blocks[0]).all(dim=1).sum())
    assert float(index.block_counts().sum()) == 20_000
