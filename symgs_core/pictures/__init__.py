"""PNG pictures of a compression job: renders of the input beside the decoded scene, the mirror planes drawn over
the scene, and rate-distortion and speed-accuracy charts. The worker stores them as the job's charts."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from ..cameras import Camera
from ..mirror import Plane
from ..report import LevelReport, Report
from ..scene import GaussianScene
from ..views import View, ViewSet
from .charts import ChartPoint, PeerPoint, job_points, rate_distortion_png, speed_accuracy_png
from .geometry import best_view, plane_box_polygon, project_polygon, scene_box, view_score
from .renders import compare_png, difference_map, mirrors_png, picture_camera, render_view


def _cameras(views: Sequence[View]) -> list[Camera]:
    """The cameras of ``views``, without rendering targets that a lazy view set has not made yet."""
    cameras = getattr(views, "cameras", None)
    return list(cameras) if cameras is not None else [view.camera for view in views]


def accepted_planes(records: Sequence[LevelReport]) -> list[tuple[int, Plane]]:
    """(level, unit plane) of each accepted level; fine-tuning leaves normals of any length, the archive's are unit."""
    return [(r.level, Plane.from_tensor(torch.tensor(r.normal, device="cpu"), r.offset)) for r in records if r.accepted]


def job_pictures(
    source_scene: GaussianScene,
    decoded_scene: GaussianScene,
    views: ViewSet,
    report: Report,
    *,
    compare_views: int = 3,
    size: int = 256,
    charts: bool = True,
) -> dict[str, bytes]:
    """PNG bytes by name: ``compare_0`` .. (the first ``compare_views`` evaluation views, uncompressed beside decoded
    with their difference), ``mirrors`` (the accepted planes over the input, from the training or evaluation camera
    that shows them best), and with ``charts`` those of ``job_charts``. ``size`` is the longest side of a render in
    pixels."""
    pictures: dict[str, bytes] = {}
    background = views.background
    for i, camera in enumerate(_cameras(views.eval)[:compare_views]):
        cam = picture_camera(camera, size)
        reference = render_view(source_scene, cam, background)
        decoded = render_view(decoded_scene, cam, background)
        name = f" ({camera.name})" if camera.name else ""
        pictures[f"compare_{i}"] = compare_png(reference, decoded, f"Evaluation view {i + 1}{name}")

    planes = accepted_planes(report.levels)
    cameras = _cameras(views.train) + _cameras(views.eval)
    if cameras:
        normals = np.array([p.normal for _, p in planes]).reshape(-1, 3)
        cam = picture_camera(cameras[best_view(cameras, normals)], round(size * 1.5))
        image = render_view(source_scene, cam, background)
        pictures["mirrors"] = mirrors_png(image, cam, planes, scene_box(source_scene.means))
    return {**pictures, **job_charts(report)} if charts else pictures


def job_charts(report: Report, peers: Sequence[PeerPoint] = ()) -> dict[str, bytes]:
    """PNG bytes by name of the charts drawn from the report alone: ``rate_distortion`` and ``speed_accuracy``,
    with ``peers`` (other formats on the same upload) beside the job's own points."""
    return {"rate_distortion": rate_distortion_png(report, peers=peers),
            "speed_accuracy": speed_accuracy_png(report, peers=peers)}  # fmt: skip


__all__ = [
    "ChartPoint",
    "accepted_planes",
    "best_view",
    "compare_png",
    "difference_map",
    "job_charts",
    "job_pictures",
    "job_points",
    "mirrors_png",
    "picture_camera",
    "plane_box_polygon",
    "project_polygon",
    "rate_distortion_png",
    "render_view",
    "scene_box",
    "speed_accuracy_png",
    "view_score",
]
