"""The matcher's internals: its space-filling-curve order, its fused attribute agreement, and order independence."""

from __future__ import annotations

import itertools

import numpy as np
import torch

from symgs_core.detect.clusters import Attributes, attributes
from symgs_core.detect.frame import normalised_frame
from symgs_core.detect.membership import Matcher, _morton_order
from symgs_core.detect.pairs import Axes, distinct_axes
from symgs_core.synthetic import Pose, synthetic_scene


def test_morton_order_of_the_cube_corners_is_the_z_curve() -> None:
    # Corner (x, y, z) in {0, 1}^3 has Morton code x + 2 y + 4 z: x varies fastest, then y, then z.
    corners = list(itertools.product((0, 1), repeat=3))  # (x, y, z), z fastest
    points = np.array([[0.5 if c else -0.5 for c in corner] for corner in corners])
    order = _morton_order(points)
    codes = [corners[i][0] + 2 * corners[i][1] + 4 * corners[i][2] for i in order]
    assert codes == list(range(8))


def test_morton_order_keeps_a_fine_grid_local() -> None:
    # A 16^3 grid in a random order (consecutive points about 10 cells apart): along the curve half of the steps
    # go to a grid neighbour and the mean step is 1.5 cells.
    axis = np.linspace(-1.0, 1.0, 16)
    grid = np.stack(np.meshgrid(axis, axis, axis, indexing="ij"), axis=-1).reshape(-1, 3)
    points = grid[np.random.default_rng(0).permutation(len(grid))]
    ordered = points[_morton_order(points)]
    steps = np.linalg.norm(np.diff(ordered, axis=0), axis=1) / (axis[1] - axis[0])
    assert np.mean(steps < 1.01) > 0.5 and steps.mean() < 1.6


def _matcher_inputs(perm: torch.Tensor | None) -> tuple[torch.Tensor, Attributes, Axes, torch.Tensor, float]:
    s = synthetic_scene("global", n=3000, seed=2, clutter=0.2, noise=0.002, pose=Pose.random(2))
    scene = s.scene if perm is None else s.scene.select(perm)
    frame = normalised_frame(scene.means.float(), 0.99)
    normal, offset = frame.plane_to_local(s.planes[0])
    return frame.to_local(scene.means.float()), attributes(scene), distinct_axes(scene, 1.5), normal, offset


def test_membership_does_not_depend_on_the_order_of_the_working_set() -> None:
    x, attrs, axes, normal, offset = _matcher_inputs(None)
    sides = Matcher(x, attrs, axes, tolerance=2.0, attribute_weight=0.6).sides(normal.double(), float(offset))
    assert sides.left.numel() > 0.25 * len(x) and sides.right.numel() > 0.25 * len(x)
    perm = torch.randperm(len(x), generator=torch.Generator().manual_seed(0))
    xp, attrs_p, axes_p, normal_p, offset_p = _matcher_inputs(perm)
    shuffled = Matcher(xp, attrs_p, axes_p, tolerance=2.0, attribute_weight=0.6).sides(
        normal_p.double(), float(offset_p)
    )
    assert torch.equal(torch.sort(perm[shuffled.left]).values, sides.left)
    assert torch.equal(torch.sort(perm[shuffled.right]).values, sides.right)


def test_agreement_is_the_product_of_the_attribute_and_axis_terms() -> None:
    x, attrs, axes, normal, _ = _matcher_inputs(None)
    matcher = Matcher(x, attrs, axes, tolerance=2.0, attribute_weight=0.6)
    n = normal.double().numpy()
    rng = np.random.default_rng(1)
    i, j = rng.integers(0, len(x), 500), rng.integers(0, len(x), 500)
    got = matcher._agreement(i, j, n)
    # The same score from the scene's own attributes (working-set indices), written out term by term.
    wi, wj = matcher.order[i], matcher.order[j]
    colour = ((attrs.rgb[wi] - attrs.rgb[wj]) / 0.15).double().square().sum(dim=1)
    opacity = ((attrs.opacity[wi] - attrs.opacity[wj]) / 0.3).double().square()
    sizes = ((attrs.log_scales[wi] - attrs.log_scales[wj]) / 0.7).double().square().sum(dim=1)
    u_i, u_j, nn = axes.u[wi].double(), axes.u[wj].double(), torch.from_numpy(n)
    cos = ((u_i - 2.0 * (u_i @ nn)[:, None] * nn) * u_j).sum(dim=1).abs()
    cos = torch.where(axes.round[wi].bool() | axes.round[wj].bool(), 1.0, cos)
    want = torch.exp(-0.5 * (colour + opacity + sizes + ((1.0 - cos) / 0.1).square()))
    np.testing.assert_allclose(got, want.numpy(), rtol=1e-5, atol=1e-6)
