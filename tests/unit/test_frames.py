"""Equivalent frames of a Gaussian: the canonical frame keeps every covariance and render, is the one closest to the
identity among the 24, and makes the rotation section smaller at the same step."""

from __future__ import annotations

import numpy as np
import torch

from symgs_core.cameras import Camera
from symgs_core.codec.frames import _octahedral, canonical_frames
from symgs_core.codec.quantize import RotationCodec
from symgs_core.render import render
from symgs_core.render.projection import quat_to_rotmat
from symgs_core.scene import GaussianScene

GROUP = _octahedral(torch.device("cpu"))[0]


def _scene(n: int, seed: int = 0) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    return GaussianScene(
        means=torch.randn(n, 3, generator=g) * 0.5,
        quats=torch.randn(n, 4, generator=g) * 3.0,  # unnormalised, as trainers leave them
        scales=torch.randn(n, 3, generator=g) * 0.5 - 3.5,
        opacities=torch.randn(n, generator=g),
        sh_dc=torch.randn(n, 3, generator=g) * 0.5,
        sh_rest=torch.randn(n, 3, 3, generator=g) * 0.1,
    )


def _covariances(scene: GaussianScene) -> torch.Tensor:
    r = quat_to_rotmat(scene.quats.double())
    s = torch.diag_embed(torch.exp(2.0 * scene.scales.double()))
    return r @ s @ r.transpose(1, 2)


def test_group_is_the_24_rotations_of_the_cube() -> None:
    matrices = quat_to_rotmat(GROUP)
    assert torch.allclose(matrices.abs().round(), matrices.abs(), atol=1e-12)  # signed permutations
    assert torch.allclose(torch.linalg.det(matrices), torch.ones(24, dtype=torch.float64))
    assert len({tuple(m.round().flatten().tolist()) for m in matrices}) == 24


def test_every_covariance_is_kept() -> None:
    scene = _scene(2000)
    canon = canonical_frames(scene)
    before, after = _covariances(scene), _covariances(canon)
    assert torch.allclose(after, before, rtol=1e-5, atol=1e-9 * float(before.abs().max()))
    for name in ("means", "opacities", "sh_dc", "sh_rest"):
        assert torch.equal(getattr(canon, name), getattr(scene, name))
    # The scales are the same three numbers per Gaussian, in another order.
    assert torch.equal(canon.scales.sort(dim=1).values, scene.scales.sort(dim=1).values)


def test_the_frame_closest_to_the_identity_is_chosen() -> None:
    scene = _scene(500, seed=1)
    canon = canonical_frames(scene)
    q = torch.nn.functional.normalize(scene.quats.double(), dim=1)
    # Brute force: |w| of q p for every group element; the canonical w is the largest of them.
    w = (q[:, None, :] * (GROUP * torch.tensor([1.0, -1.0, -1.0, -1.0], dtype=torch.float64))[None]).sum(-1).abs()
    best = w.max(dim=1).values
    assert torch.allclose(canon.quats[:, 0].double(), best, atol=1e-6)
    assert torch.allclose(canon.quats.double().norm(dim=1), torch.ones(500, dtype=torch.float64), atol=1e-6)
    assert float(canon.quats[:, 1:].abs().max()) <= np.sin(np.pi / 8) + 1e-6
    assert float(canon.quats[:, 1:].abs().sum(dim=1).sub(canon.quats[:, 0]).max()) <= 1e-6


def test_canonical_frames_are_a_fixed_point() -> None:
    once = canonical_frames(_scene(300, seed=2))
    twice = canonical_frames(once)
    assert torch.equal(twice.scales, once.scales)
    assert torch.allclose(twice.quats, once.quats, atol=1e-7)


def test_renders_are_unchanged() -> None:
    scene = _scene(300, seed=3)
    camera = Camera.look_at((0.0, 0.5, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 50.0, 64, 64)
    background = torch.zeros(3)
    before = render(scene, camera, background).image
    after = render(canonical_frames(scene), camera, background).image
    assert float(before.abs().max()) > 0.05
    assert float((after - before).abs().max()) < 1e-5


def test_rotation_section_shrinks_at_the_same_step() -> None:
    scene = _scene(20000, seed=4)
    codec = RotationCodec(0.01)
    plain = len(codec.encode(scene.quats.numpy()).payload)
    canon = len(codec.encode(canonical_frames(scene).quats.numpy()).payload)
    assert canon < 0.85 * plain  # measured 0.81 for uniformly random rotations


def test_empty_scene() -> None:
    empty = _scene(0)
    assert len(canonical_frames(empty)) == 0
