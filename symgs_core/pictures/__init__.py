"""PNG pictures of a compression job: renders of the input beside the decoded scene, the mirror planes drawn over
the scene, and rate-distortion and speed-accuracy charts. The worker stores them as the job's charts."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera
from ..mirror import Plane
from ..pipeline.levels import LevelRecord
from ..scene import GaussianScene
from ..views import ViewSet
from .charts import ChartPoint, job_points, rate_distortion_png, speed_accuracy_png
from .geometry import best_view, plane_box_polygon, project_polygon, scene_box, view_score
from .renders import compare_png, difference_map, mirrors_png, picture_camera, render_view


def _cameras(pairs: Sequence[tuple[Camera, Tensor]]) -> list[Camera]:
    """The cameras of (camera, target) pairs, without rendering targets that a lazy view set has not made yet."""
    cameras = getattr(pairs, "cameras", None)
    return list(cameras) if cameras is not None else [camera for camera, _ in pairs]


def accepted_planes(records: Sequence[LevelRecord]) -> list[tuple[int, Plane]]:
    """(level, unit plane) of each accepted level; fine-tuning leaves normals of any length, the archive's are unit."""
    return [(r.level, Plane.from_tensor(torch.tensor(r.normal), r.offset)) for r in records if r.accepted]


def job_pictures(
    source_scene: GaussianScene,
    decoded_scene: GaussianScene,
    views: ViewSet,
    records: Sequence[LevelRecord],
    report: dict,
    *,
    compare_views: int = 3,
    size: int = 256,
) -> dict[str, bytes]:
    """PNG bytes by name: ``compare_0`` .. (the first ``compare_views`` held-out views, uncompressed beside decoded
    with their difference), ``mirrors`` (the accepted planes over the input, from the training or held-out camera
    that shows them best), ``rate_distortion`` and ``speed_accuracy``. ``size`` is the longest side of a render in
    pixels; ``report`` is the pipeline's (JSON-safe) report."""
    pictures: dict[str, bytes] = {}
    background = views.background
    for i, camera in enumerate(_cameras(views.test)[:compare_views]):
        cam = picture_camera(camera, size)
        reference = render_view(source_scene, cam, background)
        decoded = render_view(decoded_scene, cam, background)
        name = f" ({camera.name})" if camera.name else ""
        pictures[f"compare_{i}"] = compare_png(reference, decoded, f"Held-out view {i + 1}{name}")

    planes = accepted_planes(records)
    cameras = _cameras(views.train) + _cameras(views.test)
    if cameras:
        normals = np.array([p.normal for _, p in planes]).reshape(-1, 3)
        cam = picture_camera(cameras[best_view(cameras, normals)], round(size * 1.5))
        image = render_view(source_scene, cam, background)
        pictures["mirrors"] = mirrors_png(image, cam, planes, scene_box(source_scene.means))
    pictures["rate_distortion"] = rate_distortion_png(records, report)
    pictures["speed_accuracy"] = speed_accuracy_png(records, report)
    return pictures


__all__ = [
    "ChartPoint",
    "accepted_planes",
    "best_view",
    "compare_png",
    "difference_map",
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
