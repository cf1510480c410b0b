"""``benchmarks/bench_twins.py``: what a residual against the mirrored partner costs, on planted halves."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from benchmarks.bench_twins import GROUPS, against_truth, measure, pairs
from symgs_core.bench.photos import photographed
from symgs_core.synthetic import synthetic_scene


def test_pairs_are_nearest_first_and_each_partner_used_once() -> None:
    dropped = np.array([[0.0, 0, 0], [0.1, 0, 0], [5.0, 0, 0]])
    mirrored = np.array([[0.05, 0, 0], [5.2, 0, 0]])
    mine, theirs = pairs(dropped, mirrored)
    # 0 and 1 are equally near partner 0: the first keeps it; 1 has no partner left (5.2 is nearer to 2).
    assert mine.tolist() == [0, 2] and theirs.tolist() == [0, 1]


def total(row: dict, which: int) -> int:
    return sum(row[g][which] for g in GROUPS)


def test_residuals_of_twins_cost_a_fraction_of_the_gaussians_and_of_independent_halves_most_of_it() -> None:
    twins = measure(synthetic_scene("global", n=3000, seed=2, sh_degree=1, capture="twins").scene)
    independent = measure(synthetic_scene("global", n=3000, seed=2, sh_degree=1, capture="independent").scene)
    assert twins["paired"] > 0.3 * twins["gaussians"] and independent["paired"] > 0.2 * independent["gaussians"]
    assert twins["near"] == twins["paired"]  # every twin lies on its partner's reflection
    assert independent["near"] < 0.01 * independent["paired"]  # independent Gaussians almost never do
    assert total(twins, 1) < 0.1 * total(twins, 0)  # a twin's residual is all zeros (measured: 1.4%)
    assert total(independent, 1) > 0.75 * total(independent, 0)  # little to predict from an independent half (88%)
    # Rendered: a twin's reflection is the Gaussian it replaces; an independent half's restores the shape, not more.
    # Columns: replaced by reflections, reflected geometry with own colours, own geometry with reflected colours,
    # left out.
    reflected, geometry, colours, left_out = twins["psnr"]
    assert reflected > 100 and geometry > 100 and colours > 100 and left_out < 20  # measured: 160.9 (inf) and 10.6 dB
    reflected, geometry, colours, left_out = independent["psnr"]
    assert left_out + 5 < reflected < 40  # measured: 21.1 and 31.3 dB
    # Each half of a reflection alone is nearer the input than the whole, and still far from the twins'
    assert reflected < geometry < 40 and reflected < colours < 40  # measured: 32.7 and 34.8 dB


def test_an_independent_half_reflected_renders_the_truth_as_well_as_the_half_it_replaces(tmp_path: Path) -> None:
    """Against photographs of the symmetric truth a reflection loses nothing; against the input's renders it does."""
    upload = photographed("global", tmp_path, n=3000, photos=2, tests=4, resolution=96)
    row = against_truth(upload, tmp_path)
    assert row is not None and row["paired"] > 0.2 * row["gaussians"]
    (input_, replaced, left_out), (replaced_renders, left_out_renders) = row["photos"], row["renders"]
    assert abs(replaced - input_) < 0.5 and left_out < replaced - 1.0  # measured: 23.76, 23.77 and 21.68 dB
    # The same scene against its own renders: the reflection no longer matches, though it restores the shape.
    assert left_out_renders + 4 < replaced_renders < 40  # measured: 25.1 and 31.8 dB
