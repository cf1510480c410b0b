"""Synthetic scenes: planted mirrors are exact (twins) or surface-level (independent captures), poses carry planes."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial import cKDTree

from symgs_core.mirror import Plane, reflect
from symgs_core.scene import GaussianScene
from symgs_core.sh import eval_sh
from symgs_core.synthetic import Pose, apply_pose, quat_to_matrix, synthetic_scene


def _same_rotation(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Largest deviation [N] between unit quaternions that may differ in sign (q and -q are one rotation)."""
    q1 = torch.nn.functional.normalize(q1, dim=-1)
    q2 = torch.nn.functional.normalize(q2, dim=-1)
    return torch.minimum((q1 - q2).abs().amax(dim=-1), (q1 + q2).abs().amax(dim=-1))


def _assert_twins(scene: GaussianScene, plane: Plane, left: torch.Tensor, right: torch.Tensor) -> None:
    mirrored = reflect(scene.select(left), *plane.tensor())
    other = scene.select(right)
    assert torch.allclose(mirrored.means, other.means, atol=1e-6 * float(scene.means.abs().max()) + 1e-6)
    assert _same_rotation(mirrored.quats, other.quats).max() < 1e-4
    assert torch.equal(mirrored.scales, other.scales)
    assert torch.equal(mirrored.sh_dc, other.sh_dc)
    assert (mirrored.sh_rest - other.sh_rest).abs().max() < 1e-5


@pytest.mark.parametrize("kind", ["global", "local", "nested"])
def test_twin_halves_are_exact_reflections_under_any_pose(kind: str) -> None:
    pose = Pose.random(7)
    s = synthetic_scene(kind, n=1500, seed=3, sh_degree=3, pose=pose)
    assert len(s.planes) == len(s.left) == len(s.right) == (1 if kind == "global" else 2)
    for plane, left, right in zip(s.planes, s.left, s.right, strict=True):
        assert len(left) == len(right) > 50
        assert not set(left.tolist()) & set(right.tolist())
        _assert_twins(s.scene, plane, left, right)


def test_planes_are_ordered_by_size_and_nested_mirror_lies_in_the_kept_half() -> None:
    local = synthetic_scene("local", n=6000, seed=1, objects=4)
    sizes = [len(a) + len(b) for a, b in zip(local.left, local.right, strict=True)]
    assert len(local.planes) == 4 and sizes == sorted(sizes, reverse=True) and sizes[-1] > 200
    nested = synthetic_scene("nested", n=3000, seed=1)
    kept = set(nested.left[0].tolist())
    assert set(nested.left[1].tolist()) <= kept and set(nested.right[1].tolist()) <= kept


def test_reflected_sh_colour_matches_at_mirrored_directions() -> None:
    s = synthetic_scene("global", n=600, seed=2, sh_degree=2, pose=Pose.random(2))
    plane = s.planes[0]
    n, _ = plane.tensor()
    dirs = torch.nn.functional.normalize(torch.randn(len(s.left[0]), 3, generator=torch.Generator().manual_seed(0)))
    h = torch.eye(3) - 2 * torch.outer(n, n)
    left, right = s.scene.select(s.left[0]), s.scene.select(s.right[0])
    assert torch.allclose(eval_sh(right.sh_coeffs(), dirs), eval_sh(left.sh_coeffs(), dirs @ h.T), atol=1e-5)


def test_independent_capture_halves_do_not_pair_one_to_one_but_lie_on_the_mirrored_surface() -> None:
    s = synthetic_scene("global", n=4000, seed=4, capture="independent")
    plane = s.planes[0]
    mirrored = reflect(s.scene.select(s.left[0]), *plane.tensor()).means.numpy()
    other = s.scene.means[s.right[0]].numpy()
    dist, _ = cKDTree(other).query(mirrored)
    spacing, _ = cKDTree(other).query(other, k=2)
    typical = float(torch.tensor(spacing[:, 1]).median())
    assert (dist < 1e-4 * typical).mean() < 0.01  # no exact twins
    assert float(torch.tensor(dist).median()) < 2.0 * typical  # but the same surface
    assert len(s.left[0]) != len(s.right[0]) or not torch.equal(
        s.scene.scales[s.left[0]].sort(0).values, s.scene.scales[s.right[0]].sort(0).values
    )


def test_noise_clutter_and_sizes() -> None:
    base = synthetic_scene("global", n=3000, seed=5)
    assert 0.8 * 3000 < len(base.scene) < 1.2 * 3000
    assert len(base.clutter) == 0
    cluttered = synthetic_scene("global", n=3000, seed=5, clutter=0.5)
    assert len(cluttered.clutter) == round(0.5 * len(base.scene))
    assert len(cluttered.scene) == len(base.scene) + len(cluttered.clutter)
    clutter = set(cluttered.clutter.tolist())
    assert not clutter & (set(cluttered.left[0].tolist()) | set(cluttered.right[0].tolist()))
    noisy = synthetic_scene("global", n=3000, seed=5, noise=0.01)
    moved = (noisy.scene.means.sort(0).values - base.scene.means.sort(0).values).abs().median()
    assert 0 < moved < 0.05
    opacity = torch.sigmoid(base.scene.opacities)
    assert (opacity >= 0.5).float().mean() > 0.8


def test_gaussians_cover_surfaces_with_overlap() -> None:
    s = synthetic_scene("global", n=5000, seed=6)
    means = s.scene.means.numpy()
    dist, _ = cKDTree(means).query(means, k=2)
    nearest = torch.tensor(dist[:, 1])
    footprint = torch.exp(s.scene.scales).sort(dim=1).values[:, 2]  # largest axis: in the surface
    assert float((3 * footprint > nearest).float().mean()) > 0.95  # neighbours overlap within 3 sigma
    thin = torch.exp(s.scene.scales).sort(dim=1).values
    assert float((thin[:, 0] < 0.5 * thin[:, 1]).float().mean()) > 0.95  # flat: surface patches


def test_deterministic_from_seed_and_scales_up() -> None:
    a = synthetic_scene("nested", n=2000, seed=9, sh_degree=1, clutter=0.2, noise=0.01, capture="independent")
    b = synthetic_scene("nested", n=2000, seed=9, sh_degree=1, clutter=0.2, noise=0.01, capture="independent")
    c = synthetic_scene("nested", n=2000, seed=10, sh_degree=1, clutter=0.2, noise=0.01, capture="independent")
    for name, t in a.scene.tensors().items():
        assert torch.equal(t, b.scene.tensors()[name])
    assert not torch.equal(a.scene.means, c.scene.means)
    big = synthetic_scene("global", n=100_000, seed=0, parts=30)
    assert 0.8 * 100_000 < len(big.scene) < 1.2 * 100_000


def test_asymmetric_scene_has_no_planted_mirror() -> None:
    s = synthetic_scene("asymmetric", n=2000, seed=0)
    assert s.planes == [] and s.left == [] and s.right == []
    assert 0.8 * 2000 < len(s.scene) < 1.2 * 2000


def test_pose_moves_scene_and_planes_together() -> None:
    pose = Pose.random(11, scale_range=(3.0, 3.0))
    assert math.isclose(pose.scale, 3.0)
    rot = pose.matrix()
    assert torch.allclose(rot @ rot.T, torch.eye(3, dtype=rot.dtype), atol=1e-12)
    assert math.isclose(float(torch.linalg.det(rot)), 1.0, abs_tol=1e-12)
    s = synthetic_scene("global", n=500, seed=1)
    moved = apply_pose(s.scene, pose)
    expected = 3.0 * s.scene.means.double() @ rot.T + torch.tensor(pose.translation, dtype=torch.float64)
    assert torch.allclose(moved.means.double(), expected, atol=1e-4)
    assert torch.allclose(moved.scales, s.scene.scales + math.log(3.0), atol=1e-6)
    # Covariances rotate: R' S R'^T = R (R_q S R_q^T) R^T.
    r_old = quat_to_matrix(torch.nn.functional.normalize(s.scene.quats.double(), dim=-1))
    r_new = quat_to_matrix(torch.nn.functional.normalize(moved.quats.double(), dim=-1))
    assert torch.allclose(r_new, rot @ r_old, atol=1e-5)


def test_invalid_arguments_are_rejected() -> None:
    with pytest.raises(ValueError, match="kind"):
        synthetic_scene("spiral", n=100)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="sh_degree"):
        synthetic_scene(n=100, sh_degree=4)
    with pytest.raises(ValueError, match="n >= 16"):
        synthetic_scene(n=3)
    with pytest.raises(ValueError, match="objects"):
        synthetic_scene("local", n=100, objects=0)
    with pytest.raises(ValueError, match="clutter"):
        synthetic_scene(n=100, clutter=-0.1)
    with pytest.raises(ValueError, match="scale"):
        Pose(scale=0.0)
