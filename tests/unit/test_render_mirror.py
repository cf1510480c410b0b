"""A scene and its reflection, seen from mirrored cameras, render as left-right mirror images of each other."""

from __future__ import annotations

import torch

from symgs_core.cameras import Camera
from symgs_core.mirror import householder, reflect, reflect_points
from symgs_core.render import render
from tests.unit._dense_reference import dense_render
from tests.unit.test_render import make_camera, random_scene

FLIP_X = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))


def mirrored_camera(cam: Camera, normal: torch.Tensor, offset: float) -> Camera:
    """The camera reflected across n.x = offset, re-handed by flipping its x axis so it stays a proper camera:
    R' = F R H, centre reflected, cx' = W - cx. Camera-space points map as (x, y, z) -> (-x, y, z)."""
    n, g = normal / normal.norm(), offset / normal.norm()  # the plane normal.x = offset, as ``reflect`` reads it
    rot = FLIP_X @ cam.R.double() @ householder(n)
    center = reflect_points(cam.center.double()[None], n, g)[0]
    return Camera(rot, -rot @ center, cam.fx, cam.fy, cam.width - cam.cx, cam.cy, cam.width, cam.height)


def assert_mirror_images(scene, cam: Camera, normal: torch.Tensor, offset: float) -> None:
    bg = torch.tensor([0.3, 0.1, 0.6], dtype=torch.float64)
    original = render(scene, cam, bg, backend="cpu")
    mirrored = render(reflect(scene, normal, offset), mirrored_camera(cam, normal, offset), bg, backend="cpu")
    assert original.alpha.max() > 0.9  # the view is not empty
    torch.testing.assert_close(mirrored.image, original.image.flip(1), rtol=0, atol=1e-9)
    torch.testing.assert_close(mirrored.alpha, original.alpha.flip(1), rtol=0, atol=1e-9)
    solid = original.alpha.flip(1) > 0.2
    torch.testing.assert_close(mirrored.depth[solid], original.depth.flip(1)[solid], rtol=1e-9, atol=0)


def test_reflection_across_a_random_plane_renders_the_mirror_image() -> None:
    g = torch.Generator().manual_seed(21)
    scene = random_scene(200, 3, seed=21)
    normal = torch.randn(3, generator=g, dtype=torch.float64)
    assert_mirror_images(scene, make_camera(), normal, 0.37)


def test_reflection_across_a_coordinate_plane_renders_the_mirror_image() -> None:
    scene = random_scene(200, 3, seed=22)
    assert_mirror_images(scene, make_camera(45, 38), torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), -0.2)


def test_gradients_reach_the_plane_through_the_reflected_scene() -> None:
    """d(loss)/d(plane) through ``reflect`` and the tile rasterizer equals the dense reference's."""
    scene = random_scene(150, 3, seed=23)
    cam = make_camera()
    bg = torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)
    target = torch.rand(cam.height, cam.width, 3, generator=torch.Generator().manual_seed(0), dtype=torch.float64)

    def plane_grads(draw) -> tuple[torch.Tensor, torch.Tensor]:
        normal = torch.tensor([0.3, 0.9, -0.2], dtype=torch.float64, requires_grad=True)
        offset = torch.tensor(0.15, dtype=torch.float64, requires_grad=True)
        both = type(scene).cat([scene, reflect(scene, normal, offset)])
        ((draw(both) - target) ** 2).sum().backward()
        return normal.grad, offset.grad

    n_grad, g_grad = plane_grads(lambda s: render(s, cam, bg, backend="cpu").image)
    n_ref, g_ref = plane_grads(lambda s: dense_render(s, cam, bg)[0])
    assert n_ref.abs().max() > 1e-3 and g_ref.abs() > 1e-3
    torch.testing.assert_close(n_grad, n_ref, rtol=1e-7, atol=0)
    torch.testing.assert_close(g_grad, g_ref, rtol=1e-7, atol=0)
