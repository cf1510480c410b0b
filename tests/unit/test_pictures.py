"""Pictures of a job: plane outlines against exact geometry, chart points against the report's arithmetic, and the
PNGs themselves (sizes, colours where a plane must be drawn), end to end through ``symgs compress --pictures``."""

from __future__ import annotations

import io
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import example, given, settings
from hypothesis import strategies as st
from PIL import Image

from service.cli import main
from symgs_core.cameras import Camera
from symgs_core.export import save_scene
from symgs_core.mirror import Plane
from symgs_core.pictures import (
    best_view,
    compare_png,
    difference_map,
    job_pictures,
    job_points,
    mirrors_png,
    plane_box_polygon,
    project_polygon,
    rate_distortion_png,
    scene_box,
    speed_accuracy_png,
    view_score,
)
from symgs_core.pictures.palette import LEVEL_COLOURS, level_colour
from symgs_core.pictures.renders import image_psnr
from symgs_core.report import Fidelity, GaussianCounts, LevelReport, Report, StageReport
from symgs_core.synthetic import synthetic_scene
from symgs_core.views import self_supervised_views

from ._samples import sample_report

LO, HI = np.full(3, -1.0), np.full(3, 1.0)


def png(data: bytes) -> Image.Image:
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    return Image.open(io.BytesIO(data)).convert("RGB")


def polygon_area(poly: np.ndarray, normal: np.ndarray) -> float:
    """Signed area of a planar polygon [K, 3] about ``normal``: positive when ordered anticlockwise."""
    return 0.5 * float(sum(np.cross(poly[i], poly[(i + 1) % len(poly)]) @ normal for i in range(len(poly))))


def test_axis_plane_cuts_the_box_in_an_ordered_square() -> None:
    poly = plane_box_polygon((1.0, 0.0, 0.0), 0.25, LO, HI)
    assert poly.shape == (4, 3)
    assert np.allclose(poly[:, 0], 0.25)
    assert {(y, z) for _, y, z in poly} == {(-1.0, -1.0), (-1.0, 1.0), (1.0, -1.0), (1.0, 1.0)}
    # Around the boundary: neighbours share a side of the square, so they differ in exactly one coordinate.
    for a, b in zip(poly, np.roll(poly, -1, axis=0)):
        assert np.count_nonzero(a[1:] != b[1:]) == 1
    assert abs(polygon_area(poly, np.array([1.0, 0, 0]))) == pytest.approx(4.0)


def test_diagonal_plane_cuts_the_cube_in_a_regular_hexagon() -> None:
    n = np.ones(3) / math.sqrt(3)
    poly = plane_box_polygon(n, 0.0, LO, HI)
    assert poly.shape == (6, 3)
    assert np.allclose(np.linalg.norm(poly, axis=1), math.sqrt(2))  # edge midpoints of the cube
    assert abs(polygon_area(poly, n)) == pytest.approx(3 * math.sqrt(3))  # a wrong order would shrink it


def test_planes_that_miss_or_graze_the_box_draw_nothing() -> None:
    assert plane_box_polygon((0.0, 0.0, 1.0), 5.0, LO, HI).shape == (0, 3)
    n = np.ones(3) / math.sqrt(3)
    assert plane_box_polygon(n, math.sqrt(3), LO, HI).shape == (0, 3)  # touches one corner
    with pytest.raises(ValueError, match="unit"):
        plane_box_polygon((1.0, 1.0, 0.0), 0.0, LO, HI)
    with pytest.raises(ValueError, match="hi >= lo"):
        plane_box_polygon((1.0, 0.0, 0.0), 0.0, HI, LO)


unit_vectors = st.tuples(*[st.floats(-1, 1)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1)


@settings(max_examples=60, deadline=None)
@given(unit_vectors, st.floats(-0.9, 0.9))
@example((1.0, 1.0, 6.4e-23), 0.0)  # through four corners, within rounding: no extra vertices between them
def test_cut_polygons_lie_on_the_plane_and_the_box_and_are_convex(v: tuple, fraction: float) -> None:
    n = np.array(v) / np.linalg.norm(v)
    offset = fraction * np.abs(n).sum()  # within the range n.x takes on the box
    poly = plane_box_polygon(n, offset, LO, HI)
    assert 3 <= len(poly) <= 6
    assert np.allclose(poly @ n, offset, atol=1e-9)
    assert np.all(np.abs(poly) <= 1 + 1e-9) and np.all(np.isclose(np.abs(poly).max(axis=1), 1.0))
    turns = [np.cross(poly[i] - poly[i - 1], poly[(i + 1) % len(poly)] - poly[i]) @ n for i in range(len(poly))]
    assert all(t > 0 for t in turns) or all(t < 0 for t in turns)


def identity_camera() -> Camera:
    return Camera(torch.eye(3), torch.zeros(3), 100.0, 100.0, 50.0, 50.0, 100, 100)


def test_projection_matches_the_pinhole_and_cuts_at_the_near_plane() -> None:
    cam = Camera.look_at((3.0, -4.0, 2.0), (0.0, 0.0, 0.0), fov_deg=60, width=120, height=80)
    points = np.array([[0.1, 0.2, -0.3], [0.5, -0.1, 0.0], [-0.2, 0.4, 0.3]])
    cam_space = points @ cam.R.double().numpy().T + cam.t.double().numpy()
    expected = (cam.K.double().numpy() @ (cam_space / cam_space[:, 2:]).T).T[:, :2]
    assert np.allclose(project_polygon(points, cam), expected, atol=1e-4)

    # A square crossing the camera plane keeps its front half, cut at z = near.
    square = np.array([[-1, 0.5, 2], [1, 0.5, 2], [1, 0.5, -1], [-1, 0.5, -1]], dtype=np.float64)
    clipped = project_polygon(square, identity_camera(), near=0.5)
    assert np.allclose(clipped, [[0, 75], [100, 75], [250, 150], [-150, 150]])
    assert project_polygon(square - [0, 0, 5], identity_camera()).shape == (0, 2)


def looking_along(direction: tuple[float, float, float]) -> Camera:
    d = np.array(direction) / np.linalg.norm(direction)
    return Camera.look_at(tuple(-5 * d), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0) if abs(d[1]) < 0.9 else (1.0, 0, 0))


def test_the_view_that_shows_planes_obliquely_wins() -> None:
    cams = [looking_along((1, 0, 0)), looking_along((0, 0, 1)), looking_along((1, 0, 1)), looking_along((1, 1, 1))]
    normal = np.array([[1.0, 0.0, 0.0]])
    scores = [view_score(c, normal) for c in cams]
    assert scores[0] == pytest.approx(0, abs=1e-6) and scores[1] == pytest.approx(0, abs=1e-6)  # face-on, edge-on
    assert scores[2] == pytest.approx(0.5)
    assert scores[3] == pytest.approx(math.sqrt(1 / 3) * math.sqrt(2 / 3))
    assert best_view(cams, normal) == 2
    # Two planes: the worst one decides. (1, 1, 1) sees both x and y planes at the same angle.
    assert best_view(cams, np.array([[1.0, 0, 0], [0, 1.0, 0]])) == 3
    assert best_view(cams, np.zeros((0, 3))) == 0


def test_scene_box_trims_floaters() -> None:
    means = torch.cat([torch.rand(990, 3) * 2 - 1, torch.full((10, 3), 100.0)])
    lo, hi = scene_box(means, trim=0.02)
    assert np.all(lo >= -1) and np.all(hi <= 1) and np.all(hi - lo > 1.8)


def record(level: int, stored_after: int, seconds: float, accepted: bool = True, **kw) -> LevelReport:  # noqa: ANN003
    values = dict(normal=(1.0, 0.0, 0.0), offset=0.0, votes=1.0, left=10, right=10, coverage=1.0,
                  psnr_before=30.0, psnr_after=35.0, reason="")  # fmt: skip
    values.update(kw)
    return LevelReport(level=level, stored_after=stored_after, seconds=seconds, accepted=accepted, **values)


SECONDS = {"load": 1.0, "views": 2.0, "detect": 3.0, "optimize": 15.0, "encode": 0.5, "evaluate": 0.25}
RECORDS = (record(0, 70, 4.0, psnr_before=math.inf), record(1, 50, 5.0), record(2, 40, 6.0, False, psnr_after=20.0))


def plain_report(**changes) -> Report:  # noqa: ANN003
    """A report without stage accounting: the baseline is the plain archive of the input."""
    base = replace(sample_report(), baseline_bytes=1000, output_bytes=600, gaussians=GaussianCounts(100, 50, 100),
                   psnr_input=math.inf, fitting=Fidelity(34.5, 36.0, 0.9), fidelity=Fidelity(34.0, 33.5, 0.9),
                   psnr_floor=30.0, seconds=SECONDS, levels=RECORDS, stages=())  # fmt: skip
    return replace(base, **changes)


def test_points_follow_the_levels_with_sizes_on_the_measured_line() -> None:
    points = job_points(plain_report())
    assert [p.kind for p in points] == ["input", "applied", "level", "applied", "level", "applied", "rolled_back",
                                        "final", "evaluated"]  # fmt: skip
    assert points[0].label == "baseline (plain codec)" and points[0].bytes == 1000 and points[0].psnr is None
    # Levels: on the line through (100 Gaussians, 1000 B) and (50, 600 B); exact at the final count.
    assert [(p.bytes, p.estimated) for p in points if p.kind in ("level", "rolled_back")] == [
        (pytest.approx(760.0), True), (600.0, False), (pytest.approx(520.0), True)]  # fmt: skip
    assert [p.psnr for p in points[1:]] == [None, 35.0, 30.0, 35.0, 30.0, 20.0, 34.5, 33.5]
    # Each level gets a third of the detection time before its own seconds; encode and evaluate close the job.
    assert [p.seconds for p in points] == pytest.approx([3, 4, 8, 9, 14, 15, 21, 21.75, 21.75])
    assert points[-1].bytes == points[-2].bytes == 600


def test_points_use_the_stage_accounting_when_the_report_has_it() -> None:
    stage = lambda name, before, after, psnr, seconds: StageReport(  # noqa: E731
        name, before, after, before - after, psnr, None, seconds)
    report = plain_report(
        baseline_bytes=400, output_bytes=300, fitting=Fidelity(37.9, 39.0, 0.9), gaussians=GaussianCounts(100, 45, 90),
        stages=(stage("mirrors", 2000, 1200, 35.0, 0.5), stage("pruning", 1200, 1000, 34.0, 1.0),
                stage("quantization", 1000, 500, 38.0, 2.0), stage("entropy_coding", 500, 300, 38.0, 0.5)),
    )  # fmt: skip
    points = job_points(report)
    assert points[0].label == "input (lossless archive)" and points[0].bytes == 2000
    levels = [p for p in points if p.kind in ("level", "rolled_back")]
    assert [p.bytes for p in levels] == pytest.approx([2000 - 800 * 30 / 50, 1200, 2000 - 800 * 60 / 50])
    stages = [p for p in points if p.kind == "stage"]
    assert [(p.label, p.bytes, p.psnr) for p in stages] == [("pruning", 1000, 34.0), ("quantization", 500, 38.0)]
    assert [p.seconds for p in stages] == pytest.approx([21 + 0.5 + 1, 21 + 0.5 + 1 + 2])
    final = points[-2]
    assert (final.bytes, final.psnr, final.seconds) == (300, 37.9, pytest.approx(25.25))


def test_charts_are_pngs_of_the_requested_size() -> None:
    for draw in (rate_distortion_png, speed_accuracy_png):
        assert png(draw(plain_report(), width=500, height=300)).size == (500, 300)
        lossless = plain_report(levels=(), fitting=Fidelity(math.inf, math.inf, 1.0))
        assert png(draw(lossless)).size == (820, 420)  # no level, lossless


def test_difference_and_compare_picture() -> None:
    a = np.zeros((20, 30, 3), dtype=np.float32)
    b = a.copy()
    b[5, 7] = [0.3, 0.6, 0.0]
    diff = difference_map(a, b)
    assert diff.shape == (20, 30) and diff[5, 7] == pytest.approx(0.3) and np.count_nonzero(diff) == 1
    assert image_psnr(a, a) == math.inf
    assert image_psnr(a, b) == pytest.approx(-10 * math.log10((0.09 + 0.36) / (20 * 30 * 3)))
    assert png(compare_png(a, b, "a view")).size == (3 * 30 + 150, 20 + 90)
    with pytest.raises(ValueError, match="same|both"):
        difference_map(a, b[:, :10])


def outline_pixels(image: Image.Image, colour: str) -> int:
    target = np.array([int(colour[i : i + 2], 16) for i in (1, 3, 5)])
    return int((np.abs(np.asarray(image).astype(int) - target).max(axis=2) <= 12).sum())


def test_mirror_planes_are_outlined_in_their_level_colours() -> None:
    cam = Camera.look_at((3.0, 2.0, 1.5), (0.0, 0.0, 0.0), fov_deg=50, width=96, height=96)
    black = np.zeros((96, 96, 3), dtype=np.float32)
    planes = [(0, Plane((1.0, 0.0, 0.0), 0.0)), (1, Plane((0.0, 1.0, 0.0), 0.3))]
    drawn = png(mirrors_png(black, cam, planes, (LO, HI)))
    for level, _ in planes:
        assert outline_pixels(drawn, level_colour(level)) > 40, level
    empty = png(mirrors_png(black, cam, [], (LO, HI)))
    assert all(outline_pixels(empty, colour) == 0 for colour in LEVEL_COLOURS[:2])
    with pytest.raises(ValueError, match="image is"):
        mirrors_png(black[:50], cam, planes, (LO, HI))


def test_job_pictures_of_a_symmetric_scene() -> None:
    made = synthetic_scene("global", n=300, seed=2)
    views = self_supervised_views(made.scene, train=3, fit=1, eval=2, resolution=32, eval_resolution=32,
                                  background=torch.zeros(3))  # fmt: skip
    plane = made.planes[0]
    normal = tuple(2 * v for v in plane.normal)  # unnormalised
    report = plain_report(gaussians=GaussianCounts(300, 150, 300),
                          levels=(record(0, 150, 1.0, normal=normal, offset=2 * plane.offset),))  # fmt: skip
    pictures = job_pictures(made.scene, made.scene, views, report, size=48)
    assert set(pictures) == {"compare_0", "compare_1", "mirrors", "rate_distortion", "speed_accuracy"}
    assert png(pictures["compare_0"]).size == (3 * 48 + 150, 48 + 90)
    assert outline_pixels(png(pictures["mirrors"]), level_colour(0)) > 20


def test_compress_command_writes_the_pictures(tmp_path: Path) -> None:
    scene = tmp_path / "scene.ply"
    save_scene(synthetic_scene("global", n=300, seed=1).scene, scene)
    out = tmp_path / "pictures"
    tiny = ["--iterations", "2", "--train-views", "2", "--fit-views", "1", "--eval-views", "1", "--resolution", "24",
            "--eval-resolution", "24", "--max-levels", "1"]
    argv = ["compress", str(scene), "-o", str(tmp_path / "scene.symgs"), "--pictures", str(out), "--quiet", *tiny]
    assert main(argv) == 0
    assert {p.name for p in out.iterdir()} == {"compare_0.png", "mirrors.png", "rate_distortion.png",
                                               "speed_accuracy.png"}  # fmt: skip
    for path in out.iterdir():
        png(path.read_bytes())
