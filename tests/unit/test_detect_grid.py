"""The accumulator's seam, its peaks, and the pair enumeration and sampling that feed it."""

from __future__ import annotations

import math

import torch

from symgs_core.detect.clusters import Clusters, rgb_to_hsv
from symgs_core.detect.grid import GridSpec, top_peaks
from symgs_core.detect.pairs import candidate_pairs, enumerate_pairs, sample_pairs
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
