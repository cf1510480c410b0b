"""Where mirror planes fall in a picture: a plane cut to the scene's box, projected through a camera.

Plain float64 numpy: these are a handful of points per plane, and exactness matters more than speed.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..cameras import Camera

_SAMPLE = 1 << 20  # quantiles of a larger scene are taken on an evenly strided sample of this many points


def scene_box(means: Tensor, trim: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Corners lo [3], hi [3] of the axis-aligned box holding all but ``trim`` of the points at each end, per axis.

    Trimming keeps a few floaters far from the object from stretching a plane's drawing across the picture."""
    if means.ndim != 2 or means.shape[1] != 3 or means.shape[0] == 0:
        raise ValueError(f"means must be a non-empty [N, 3] tensor, got shape {tuple(means.shape)}")
    if not 0 <= trim < 0.5:
        raise ValueError(f"trim must be in [0, 0.5), got {trim}")
    points = means.detach().to("cpu", torch.float64)
    points = points[:: max(1, len(points) // _SAMPLE)]
    q = points.new_tensor([trim, 1.0 - trim])
    lo, hi = torch.quantile(points, q, dim=0).numpy()
    return lo, hi


_CORNERS = np.array([[(i >> a) & 1 for a in range(3)] for i in range(8)], dtype=np.float64)  # [8, 3] in {0, 1}
_EDGES = [(i, i | (1 << a)) for i in range(8) for a in range(3) if not (i >> a) & 1]  # 12 pairs differing in one axis


def plane_box_polygon(
    normal: np.ndarray | tuple[float, float, float], offset: float, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """The polygon [K, 3] (K in 3..6, in order around its boundary) where the plane n.x = offset cuts the box
    [lo, hi]; [0, 3] when the plane misses the box or only touches it at an edge or corner."""
    n = np.asarray(normal, dtype=np.float64)
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    if n.shape != (3,) or not np.isclose(np.linalg.norm(n), 1.0, atol=1e-4):
        raise ValueError(f"normal must be a unit 3-vector, got {n.tolist()}")
    if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi >= lo):
        raise ValueError(f"box corners must be 3-vectors with hi >= lo, got lo={lo.tolist()}, hi={hi.tolist()}")
    corners = lo + _CORNERS * (hi - lo)
    scale = max(float(np.abs(hi - lo).max()), 1e-12)
    d = corners @ n - offset
    d[np.abs(d) <= 1e-12 * scale] = 0.0  # corners on the plane are vertices; their edges then cross nowhere else
    points = [corners[i] for i in range(8) if d[i] == 0.0]
    for a, b in _EDGES:
        if d[a] * d[b] < 0:
            points.append(corners[a] + (corners[b] - corners[a]) * (d[a] / (d[a] - d[b])))
    if not points:
        return np.zeros((0, 3))
    unique: list[np.ndarray] = []
    for p in points:
        if all(np.linalg.norm(p - u) > 1e-9 * scale for u in unique):
            unique.append(p)
    if len(unique) < 3:
        return np.zeros((0, 3))
    poly = np.stack(unique)
    # Order by angle about the centroid, in a basis (u, v) of the plane.
    u = np.cross(n, np.eye(3)[int(np.argmin(np.abs(n)))])
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    rel = poly - poly.mean(axis=0)
    return poly[np.argsort(np.arctan2(rel @ v, rel @ u))]


def project_polygon(points: np.ndarray, camera: Camera, near: float = 1e-3) -> np.ndarray:
    """Pixel coordinates [M, 2] (x right, y down) of a planar polygon [K, 3] seen by ``camera``, after cutting away
    the part closer than ``near`` (camera-space z), so a plane through the camera still draws; [0, 2] when all of
    it is behind."""
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be [K, 3], got shape {points.shape}")
    R = camera.R.detach().to("cpu", torch.float64).numpy()
    t = camera.t.detach().to("cpu", torch.float64).numpy()
    cam = points @ R.T + t
    clipped: list[np.ndarray] = []
    for i in range(len(cam)):  # Sutherland-Hodgman against the single plane z = near
        a, b = cam[i], cam[(i + 1) % len(cam)]
        if a[2] >= near:
            clipped.append(a)
        if (a[2] >= near) != (b[2] >= near):
            clipped.append(a + (b - a) * ((near - a[2]) / (b[2] - a[2])))
    if len(clipped) < 3:
        return np.zeros((0, 2))
    c = np.stack(clipped)
    return np.stack([camera.fx * c[:, 0] / c[:, 2] + camera.cx, camera.fy * c[:, 1] / c[:, 2] + camera.cy], axis=1)


def view_score(camera: Camera, normals: np.ndarray) -> float:
    """How well ``camera`` shows planes with these unit normals [L, 3]: the worst plane's |cos a| sin a, where a is
    the angle between the viewing direction and its normal. 0 for a plane seen edge-on (a line) or face-on (it
    covers everything); 0.5 at 45 degrees."""
    normals = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(normals) == 0:
        return 0.0
    forward = camera.R.detach().to("cpu", torch.float64).numpy()[2]  # the camera's z axis, in world coordinates
    c = np.abs(normals @ forward)
    return float((c * np.sqrt(np.clip(1.0 - c * c, 0.0, None))).min())


def best_view(cameras: list[Camera], normals: np.ndarray) -> int:
    """Index of the camera with the highest ``view_score`` (the first on ties; the first without planes)."""
    if not cameras:
        raise ValueError("best_view needs at least one camera")
    scores = [view_score(cam, normals) for cam in cameras]
    return int(np.argmax(scores))
