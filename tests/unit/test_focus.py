"""What a capture's cameras look at (``cameras.focus``), and the mirror of an object found among its surroundings."""

from __future__ import annotations

import math

import pytest
import torch

from symgs_core.cameras import Camera, fibonacci_directions, focus
from symgs_core.detect import DetectConfig, detect
from symgs_core.mirror import Plane
from symgs_core.synthetic import synthetic_scene

TARGET = (0.3, -1.2, 0.7)


def _orbit(distances: list[float], fov_deg: float = 60.0, width: int = 256, height: int = 256) -> list[Camera]:
    target = torch.tensor(TARGET, dtype=torch.float64)
    directions = [d for d in fibonacci_directions(24).double() if abs(float(d[2])) < 0.9]
    return [
        Camera.look_at(target + distances[i % len(distances)] * d, target, fov_deg=fov_deg, width=width, height=height)
        for i, d in enumerate(directions)
    ]


def test_the_point_all_cameras_look_at_and_the_ball_the_median_camera_frames() -> None:
    found = focus(_orbit([3.0]))
    assert found is not None
    assert torch.allclose(found.centre, torch.tensor(TARGET, dtype=torch.float64), atol=1e-5)
    assert found.radius == pytest.approx(3.0 * math.tan(math.radians(30.0)), rel=1e-5)


def test_the_radius_is_the_median_cameras_and_the_narrower_sides() -> None:
    # Landscape frames: the vertical half-field is the narrower; distances 2, 3 and 4 in turn: the median is 3.
    cameras = _orbit([2.0, 3.0, 4.0], width=320, height=160)
    found = focus(cameras)
    assert found is not None
    half = cameras[0].cy / cameras[0].fy
    assert half < cameras[0].cx / cameras[0].fx
    assert found.radius == pytest.approx(3.0 * half, rel=1e-5)


def test_cameras_that_look_at_no_one_point_have_no_focus() -> None:
    forward = [Camera.look_at((x, 0.0, 0.0), (x, 5.0, 0.0)) for x in (-1.0, 0.0, 1.0, 2.0)]
    assert focus(forward) is None  # a forward-facing capture: parallel axes
    outward = [Camera.look_at(3.0 * d, 6.0 * d) for d in fibonacci_directions(12).double() if abs(float(d[2])) < 0.9]
    assert focus(outward) is None  # the axes cross behind every camera
    assert focus(_orbit([3.0])[:1]) is None


def test_the_ball_holds_the_points_inside_it() -> None:
    found = focus(_orbit([3.0]))
    assert found is not None
    target = torch.tensor(TARGET)
    points = torch.stack([target, target + torch.tensor([found.radius * 0.99, 0, 0]), target + found.radius * 1.01])
    assert found.holds(points).tolist() == [0, 1]


def _is(found: Plane, planted: Plane) -> bool:
    """The same plane: normals within 0.5 degrees and offsets within 0.02 (the object is about 1 across)."""
    sign = 1.0 if sum(a * b for a, b in zip(found.normal, planted.normal, strict=True)) > 0 else -1.0
    return found.angle_deg(planted) < 0.5 and abs(sign * found.offset - planted.offset) < 0.02


def test_an_object_among_its_surroundings_is_found_where_the_cameras_look() -> None:
    # A symmetric object standing on a slab of asymmetric Gaussians, 20 times as many: the object is 5% of the scene
    # and touches what surrounds it, so neither the whole set nor a separate part shows its mirror.
    made = synthetic_scene("global", n=3000, seed=3, sh_degree=1, surroundings=20.0)
    scene, plane = made.scene, made.planes[0]
    centre = made.scene.means[made.left[0]].median(dim=0).values.double()
    cameras = [Camera.look_at(centre + 2.5 * d, centre, fov_deg=60) for d in fibonacci_directions(20).double()
               if float(d[2]) > -0.3]  # fmt: skip
    config = DetectConfig(max_mirrors=2)
    assert not any(_is(m.plane, plane) for m in detect(scene, config))
    found = detect(scene, config, focus=focus(cameras))
    assert found and _is(found[0].plane, plane)
    members = torch.cat([found[0].left, found[0].right])
    planted = torch.cat([made.left[0], made.right[0]])
    assert torch.isin(members, planted).float().mean() > 0.9  # the object's own Gaussians, few of the surroundings
    assert torch.isin(planted, members).float().mean() > 0.9


def test_a_job_searches_where_its_photographs_look_then_the_whole_scene(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    """With photographs the level first searches their focus; where the mirror found there cannot pay (here made
    to drop two Gaussians), the whole scene's is tried at the same level. Without photographs there is no focus."""
    from dataclasses import replace

    from symgs_core.bench.photos import photographed
    from symgs_core.config import CompressConfig
    from symgs_core.pipeline import compress

    upload = photographed("global", tmp_path, n=600, photos=8, tests=2, resolution=48, sh_degree=0, capture="twins")
    seen: list[object] = []

    def spy(scene, config=None, *, exclude=(), focus=None):  # noqa: ANN001, ANN202
        seen.append(focus)
        found = detect(scene, config, exclude=exclude, focus=focus)
        if focus is None or not found:
            return found
        return [replace(found[0], left=found[0].left[:2], right=found[0].right[:2], found_in="focus")]

    monkeypatch.setattr("symgs_core.detect.detect", spy)  # the package's name, which the level loop imports
    small = CompressConfig.for_preset(iterations=20, fit_views=3, eval_views=2, eval_resolution=48, max_levels=1,
                                      pictures=False)  # fmt: skip
    report = compress(upload, images=tmp_path, config=small, charts=False).report
    assert len(seen) == 2 and seen[0] is not None and seen[1] is None  # the focus, then the whole scene
    centre = upload.means.median(dim=0).values.double()
    assert float((seen[0].centre.cpu() - centre).norm()) < 0.3  # the generated object's middle, about 1 across
    assert report.levels and all(level.found_in == "scene" for level in report.levels)
    assert report.levels[0].right > 2  # the whole scene's membership, not the focus's two Gaussians
    seen.clear()
    compress(upload, config=small, charts=False)
    assert seen and all(f is None for f in seen)  # cameras placed around the scene say nothing of what matters
