"""The coding order of the stored set: Morton codes, grouping by bit row, and what it does to the masks."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from symgs_core.codec import coding_order, morton_codes
from symgs_core.codec.masks import MASKS, column_runs
from symgs_core.mirror import expand
from symgs_core.scene import GaussianScene
from tests.unit.test_archive import random_contents


def naive_morton(q: np.ndarray) -> int:
    code = 0
    for bit in range(21):
        for axis in range(3):
            code |= ((int(q[axis]) >> bit) & 1) << (3 * bit + axis)
    return code


def test_morton_codes_interleave_the_quantised_axes() -> None:
    rng = np.random.default_rng(0)
    q = rng.integers(0, 1 << 21, size=(200, 3))
    q[0] = 0
    q[1] = (1 << 21) - 1  # the corners fix the bounding box, so quantisation is the identity
    codes = morton_codes(torch.from_numpy(q.astype(np.float64)))
    assert codes.tolist() == [naive_morton(row) for row in q]
    assert int(codes[1]) == (1 << 63) - 1


def test_morton_order_keeps_neighbours_close() -> None:
    points = torch.rand(5000, 3, generator=torch.Generator().manual_seed(1))
    ordered = points[torch.argsort(morton_codes(points))]
    step = (ordered[1:] - ordered[:-1]).norm(dim=1).mean()
    random_step = (points[1:] - points[:-1]).norm(dim=1).mean()
    assert step < 0.15 * random_step, (float(step), float(random_step))


def test_morton_codes_of_degenerate_sets() -> None:
    assert morton_codes(torch.zeros(0, 3)).shape == (0,)
    assert morton_codes(torch.ones(4, 3)).tolist() == [0, 0, 0, 0]
    with pytest.raises(ValueError, match="finite"):
        morton_codes(torch.tensor([[0.0, float("nan"), 0.0]]))
    with pytest.raises(ValueError, match=r"shape \(N, 3\)"):
        morton_codes(torch.zeros(4, 2))


def test_coding_order_groups_bit_rows_then_follows_the_curve() -> None:
    contents = random_contents(3000, 0, 3, special=False)
    perm = coding_order(contents.stored, contents.bits)
    assert sorted(perm.tolist()) == list(range(3000))
    bits = contents.bits[perm]
    keys = (bits.long() * torch.tensor([4, 2, 1])).sum(dim=1)
    assert bool((keys[1:] >= keys[:-1]).all())
    for level in range(3):
        assert len(column_runs(bits[:, level].numpy())) <= 2 ** (level + 1)
    codes = morton_codes(contents.stored.means)[perm]
    same_group = keys[1:] == keys[:-1]
    assert bool((codes[1:][same_group] >= codes[:-1][same_group]).all())
    assert torch.equal(coding_order(contents.stored, contents.bits), perm)  # deterministic


def test_ordered_masks_cost_almost_nothing() -> None:
    contents = random_contents(20_000, 0, 4, special=False)
    shuffled = MASKS.encode(contents.bits.numpy())
    perm = coding_order(contents.stored, contents.bits)
    ordered = MASKS.encode(contents.bits[perm].numpy())
    assert len(ordered.payload) < 100 < len(shuffled.payload) / 50, (len(ordered.payload), len(shuffled.payload))


def test_reordering_changes_the_expansion_only_by_a_permutation() -> None:
    contents = random_contents(200, 1, 3, special=False)
    normals = torch.tensor([p.normal for p in contents.planes], dtype=torch.float32)
    offsets = torch.tensor([p.offset for p in contents.planes], dtype=torch.float32)
    perm = coding_order(contents.stored, contents.bits)
    moved = contents.permuted(perm)
    before, origin_before = expand(contents.stored, normals, offsets, contents.bits)
    after, origin_after = expand(moved.stored, normals, offsets, moved.bits)
    # Copies of one stored Gaussian keep their relative order, so a stable sort by source lines them up.
    by_source_before = torch.argsort(origin_before, stable=True)
    by_source_after = torch.argsort(perm[origin_after], stable=True)
    for name, value in before.tensors().items():
        torch.testing.assert_close(
            after.tensors()[name][by_source_after], value[by_source_before], rtol=1e-6, atol=1e-5
        )


def test_coding_order_rejects_mismatched_bits() -> None:
    stored = GaussianScene.empty()
    with pytest.raises(ValueError, match=r"bits must have shape \(0, L\+1\)"):
        coding_order(stored, torch.zeros(3, 1, dtype=torch.bool))
    assert coding_order(stored, torch.zeros(0, 2, dtype=torch.bool)).shape == (0,)
