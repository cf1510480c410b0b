"""Reflection of a Gaussian set across a plane (``symgs_core/mirror.py`` states the formulas), against exact oracles."""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from symgs_core.cameras import Camera
from symgs_core.mirror import Plane, householder, reflect, reflect_points, reflect_quats
from symgs_core.scene import SH_REST_COUNT, GaussianScene
from symgs_core.sh import eval_sh, sh_basis, sh_to_rgb, sh_transform_matrix

# Indices (DC = 0) of the coefficients whose sign flips under each coordinate-plane reflection.
SIGN_FLIPS = {0: (3, 4, 7, 10, 13, 15), 1: (1, 4, 5, 9, 10, 11), 2: (2, 5, 7, 10, 12, 14)}


def random_scene(n: int, degree: int, seed: int, dtype: torch.dtype = torch.float64) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    r = lambda *shape: torch.randn(*shape, generator=g, dtype=dtype)
    return GaussianScene(r(n, 3), r(n, 4), r(n, 3) * 0.3 - 2, r(n), r(n, 3), r(n, SH_REST_COUNT[degree], 3) * 0.3)


def random_planes(count: int, seed: int) -> list[tuple[Tensor, float]]:
    g = torch.Generator().manual_seed(seed)
    normals = torch.nn.functional.normalize(torch.randn(count, 3, generator=g, dtype=torch.float64), dim=-1)
    offsets = torch.randn(count, generator=g, dtype=torch.float64)
    return [(n, float(o)) for n, o in zip(normals, offsets, strict=True)]


def rotmat(q: Tensor) -> Tensor:
    """Rotation matrices [N, 3, 3] of Hamilton quaternions [N, 4] (w, x, y, z), normalised first."""
    w, x, y, z = torch.nn.functional.normalize(q, dim=-1).unbind(-1)
    return torch.stack(
        [
            torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def covariance(scene: GaussianScene) -> Tensor:
    r = rotmat(scene.quats)
    s2 = torch.diag_embed(torch.exp(2 * scene.scales))
    return r @ s2 @ r.transpose(-1, -2)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_reflecting_twice_is_the_identity(degree: int) -> None:
    scene = random_scene(50, degree, seed=degree)
    for normal, offset in random_planes(4, seed=10 + degree):
        twice = reflect(reflect(scene, normal, offset), normal, offset)
        for name in ("means", "scales", "opacities", "sh_dc", "sh_rest"):
            torch.testing.assert_close(getattr(twice, name), getattr(scene, name), rtol=0, atol=1e-12)
        # q'' = (0, n)(0, n) q = -q: the same rotation
        torch.testing.assert_close(twice.quats, -scene.quats, rtol=0, atol=1e-12)


def test_reflected_means_are_mirror_images() -> None:
    scene = random_scene(100, 0, seed=1)
    for normal, offset in random_planes(5, seed=2):
        mirrored = reflect(scene, normal, offset).means
        mid = (mirrored + scene.means) / 2
        torch.testing.assert_close(mid @ normal, torch.full((100,), offset, dtype=torch.float64))
        step = mirrored - scene.means
        torch.testing.assert_close(torch.linalg.cross(step, normal.expand_as(step), dim=-1), torch.zeros_like(step))
        on_plane = scene.means - ((scene.means @ normal - offset)[:, None]) * normal
        torch.testing.assert_close(reflect_points(on_plane, normal, offset), on_plane)


def test_reflected_covariance_is_h_sigma_h() -> None:
    scene = random_scene(200, 0, seed=3)
    for normal, offset in random_planes(6, seed=4):
        h = householder(normal)
        mirrored = reflect(scene, normal, offset)
        torch.testing.assert_close(covariance(mirrored), h @ covariance(scene) @ h, rtol=0, atol=1e-12)
        assert torch.equal(mirrored.scales, scene.scales) and torch.equal(mirrored.opacities, scene.opacities)


def test_reflected_rotation_is_the_half_turn_about_the_normal_times_r() -> None:
    quats = random_scene(64, 0, seed=5).quats
    for normal, _ in random_planes(4, seed=6):
        half_turn = 2 * torch.outer(normal, normal) - torch.eye(3, dtype=torch.float64)
        torch.testing.assert_close(rotmat(reflect_quats(quats, normal)), half_turn @ rotmat(quats), rtol=0, atol=1e-12)
        # a proper rotation: the reflection's improper part goes into the half turn, not the quaternion
        assert torch.allclose(
            torch.linalg.det(rotmat(reflect_quats(quats, normal))), torch.ones(64, dtype=torch.float64)
        )


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_reflected_sh_colour_is_the_colour_at_the_mirrored_direction(degree: int) -> None:
    scene = random_scene(300, degree, seed=20 + degree)
    g = torch.Generator().manual_seed(30 + degree)
    dirs = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=-1)
    for normal, offset in random_planes(5, seed=40 + degree):
        mirrored = reflect(scene, normal, offset)
        mirrored_dirs = dirs @ householder(normal).T
        torch.testing.assert_close(
            eval_sh(mirrored.sh_coeffs(), dirs), eval_sh(scene.sh_coeffs(), mirrored_dirs), rtol=0, atol=1e-12
        )
        torch.testing.assert_close(sh_to_rgb(mirrored.sh_coeffs(), dirs), sh_to_rgb(scene.sh_coeffs(), mirrored_dirs))


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_coordinate_plane_sign_tables(axis: int) -> None:
    normal = torch.zeros(3, dtype=torch.float64)
    normal[axis] = 1.0
    signs = torch.ones(16, dtype=torch.float64)
    signs[list(SIGN_FLIPS[axis])] = -1.0
    # the table is what the basis itself does under the reflection ...
    dirs = torch.nn.functional.normalize(
        torch.randn(500, 3, generator=torch.Generator().manual_seed(axis), dtype=torch.float64), dim=-1
    )
    flipped = dirs.clone()
    flipped[:, axis] = -flipped[:, axis]
    torch.testing.assert_close(sh_basis(3, flipped), sh_basis(3, dirs) * signs, rtol=0, atol=1e-14)
    # ... and what the transform matrix and the reflection of a scene produce, for every degree
    for degree in range(4):
        m = (degree + 1) ** 2
        t = sh_transform_matrix(householder(normal), degree)
        torch.testing.assert_close(t, torch.diag(signs[:m]), rtol=0, atol=1e-12)
        scene = random_scene(20, degree, seed=axis)
        mirrored = reflect(scene, normal, 0.7)
        torch.testing.assert_close(mirrored.sh_rest, scene.sh_rest * signs[1:m, None], rtol=0, atol=1e-12)
        assert torch.equal(mirrored.sh_dc, scene.sh_dc)


def test_float32_scene_stays_float32() -> None:
    scene = random_scene(10, 3, seed=7, dtype=torch.float32)
    mirrored = reflect(scene, torch.tensor([0.0, 0.6, 0.8]), 0.1)
    assert all(t.dtype == torch.float32 for t in mirrored.tensors().values())
    torch.testing.assert_close(reflect(mirrored, torch.tensor([0.0, 0.6, 0.8]), 0.1).sh_rest, scene.sh_rest)


def test_non_unit_normals_describe_the_same_plane() -> None:
    scene = random_scene(30, 2, seed=8)
    normal, offset = random_planes(1, seed=9)[0]
    a = reflect(scene, normal, offset)
    b = reflect(scene, 3.5 * normal, 3.5 * offset)
    for name, value in a.tensors().items():
        torch.testing.assert_close(b.tensors()[name], value, rtol=0, atol=1e-12)
    plane = Plane.from_tensor(3.5 * normal, 3.5 * offset)
    assert plane.offset == pytest.approx(offset) and plane.normal == pytest.approx(tuple(normal.tolist()))
    flipped = Plane(tuple((-normal).tolist()), -offset).canonical()
    assert flipped.canonical() == flipped and max(flipped.normal, key=abs) > 0
    assert flipped.offset == pytest.approx(plane.canonical().offset)
    with pytest.raises(ValueError, match="unit length"):
        Plane((1.0, 1.0, 0.0), 0.0)


@pytest.mark.parametrize("degree", [1, 3])
def test_gradients_reach_the_plane(degree: int) -> None:
    scene = random_scene(6, degree, seed=11)
    normal = torch.tensor([0.3, -0.5, 0.8], dtype=torch.float64, requires_grad=True)
    offset = torch.tensor(0.2, dtype=torch.float64, requires_grad=True)

    def outputs(n: Tensor, g: Tensor) -> tuple[Tensor, ...]:
        mirrored = reflect(scene, n, g)
        return mirrored.means, mirrored.quats, mirrored.sh_rest

    assert torch.autograd.gradcheck(outputs, (normal, offset))
    means, quats, rest = outputs(normal, offset)
    grad_n, grad_g = torch.autograd.grad(means.sum() + quats.sum() + rest.sum(), (normal, offset))
    assert grad_n.abs().sum() > 0 and grad_g.abs() > 0


def mirrored_camera(camera: Camera, normal: Tensor, offset: float) -> Camera:
    """The camera reflected across the plane, with its x axis negated to stay right-handed: it sees the
    left-right mirror image of what the original camera sees."""
    h = householder(normal.double())
    c2w = camera.R.double().T
    axes = h @ c2w
    axes[:, 0] = -axes[:, 0]
    center = reflect_points(camera.center.double()[None], normal.double(), offset)[0]
    r = axes.T
    return Camera(
        r.float(), (-r @ center).float(), camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height
    )


def test_rendering_the_reflection_from_the_mirrored_camera_gives_the_mirror_image() -> None:
    try:
        from symgs_core.render import render
    except ImportError:
        pytest.skip("symgs_core.render is not available in this build")
    scene = random_scene(300, 2, seed=12, dtype=torch.float32)
    scene = scene.with_(scales=scene.scales - 1.0, opacities=scene.opacities + 1.0)
    normal = torch.nn.functional.normalize(torch.tensor([0.4, -0.3, 0.85]), dim=0)
    offset = 0.3
    camera = Camera.look_at((4.0, 3.0, 2.0), (0.0, 0.0, 0.0), fov_deg=60.0, width=48, height=40)
    original = render(scene, camera, background=torch.tensor([0.2, 0.3, 0.4])).image
    mirrored = render(
        reflect(scene, normal, offset),
        mirrored_camera(camera, normal, offset),
        background=torch.tensor([0.2, 0.3, 0.4]),
    ).image
    assert original.shape == (40, 48, 3) and original.std() > 0.05
    torch.testing.assert_close(mirrored, original.flip(1), rtol=0, atol=2e-4)
    assert not math.isclose(float((original - original.flip(1)).abs().max()), 0.0, abs_tol=1e-2)


def test_plane_angle_and_gap_against_exact_values() -> None:
    x = Plane((1.0, 0.0, 0.0), 0.5)
    tilted = Plane((math.cos(math.radians(30)), math.sin(math.radians(30)), 0.0), 0.0)
    assert x.angle_deg(tilted) == pytest.approx(30.0, abs=1e-9)
    flipped = Plane((-1.0, 0.0, 0.0), -0.2)  # x = 0.2, its normal turned the other way
    assert x.angle_deg(flipped) == pytest.approx(0.0, abs=1e-9)
    assert x.gap_at(flipped, torch.tensor([3.0, 1.0, -2.0])) == pytest.approx(0.3, abs=1e-12)
    # At (0, 2, 0) the signed distances are -0.5 (to x = 0.5) and +1.0 (to the tilted plane through the origin).
    assert x.gap_at(tilted, torch.tensor([0.0, 2.0, 0.0])) == pytest.approx(1.5, abs=1e-12)
