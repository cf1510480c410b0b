"""Pinhole cameras, OpenCV convention: world-to-camera (R, t), x right, y down, z forward; pixel centres at +0.5.

A camera is built on the CPU (``HOST``) from host numbers; a job moves it to its scene's device where it renders
(``Camera.to``), and the intrinsics and view matrix follow its rotation's device."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from typing import NamedTuple

import torch
from torch import Tensor

from .devices import HOST

COORDINATE_CONVENTION = "opencv: world-to-camera extrinsics, camera x right, y down, z forward"
NEAR_PLANE = 0.01  # camera-space depth below which Gaussians are not drawn (gsplat's default)
# Cameras placed around a scene keep their near plane within this share of its radius: a scene in tiny units (a
# small object in metres, or smaller) would otherwise lie behind it and render blank.
NEAR_SHARE = 0.1
# Optical axes cross where they leave the least-squares point well determined in every direction: the smallest
# eigenvalue of their mean projector (I - d d^T) at least this. Cameras that all face one way (a forward-facing
# capture) leave it near 0: they look at no one point. Cameras in one ring around an object give 0.5.
CROSSING = 0.02


@dataclass
class Camera:
    """A pinhole camera.

    R [3, 3] and t [3] map world points to camera space: x_cam = R x_world + t.
    fx, fy, cx, cy in pixels; width, height in pixels; ``near`` the depth below which nothing is drawn.
    """

    R: Tensor
    t: Tensor
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    name: str = ""
    near: float = NEAR_PLANE

    def __post_init__(self) -> None:
        if tuple(self.R.shape) != (3, 3) or tuple(self.t.shape) != (3,):
            raise ValueError(f"camera R must be (3, 3) and t (3,), got {tuple(self.R.shape)}, {tuple(self.t.shape)}")
        if self.width <= 0 or self.height <= 0:
            raise ValueError(f"camera size must be positive, got {self.width}x{self.height}")
        if not (self.fx > 0 and self.fy > 0):
            raise ValueError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if not 0.0 < self.near < math.inf:
            raise ValueError(f"the near plane must be positive and finite, got {self.near}")

    # Kept once built: a fine-tune renders one camera thousands of times, and each build copies to its device.
    @cached_property
    def K(self) -> Tensor:
        """Intrinsics [3, 3]."""
        return torch.tensor(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]],
            dtype=self.R.dtype,
            device=self.R.device,
        )

    @cached_property
    def viewmat(self) -> Tensor:
        """World-to-camera [4, 4]."""
        m = torch.eye(4, dtype=self.R.dtype, device=self.R.device)
        m[:3, :3] = self.R
        m[:3, 3] = self.t
        return m

    @property
    def center(self) -> Tensor:
        """Camera centre in world coordinates [3]."""
        return -self.R.T @ self.t

    def to(self, device: torch.device | str) -> Camera:
        return replace(self, R=self.R.to(device), t=self.t.to(device))

    def resized(self, width: int, height: int) -> Camera:
        """The same view at another resolution (intrinsics scaled)."""
        sx, sy = width / self.width, height / self.height
        return replace(self, fx=self.fx * sx, fy=self.fy * sy, cx=self.cx * sx, cy=self.cy * sy, width=width,
                       height=height)  # fmt: skip

    @staticmethod
    def look_at(
        eye: Tensor | tuple[float, float, float],
        target: Tensor | tuple[float, float, float],
        up: Tensor | tuple[float, float, float] = (0.0, 0.0, 1.0),
        fov_deg: float = 50.0,
        width: int = 256,
        height: int = 256,
        name: str = "",
        near: float = NEAR_PLANE,
    ) -> Camera:
        """A camera at ``eye`` looking at ``target``; ``fov_deg`` is the horizontal field of view."""
        eye_t = torch.as_tensor(eye, dtype=torch.float64, device=HOST)
        forward = torch.as_tensor(target, dtype=torch.float64, device=HOST) - eye_t
        if forward.norm() == 0:
            raise ValueError("look_at: eye and target coincide")
        forward = forward / forward.norm()
        up_t = torch.as_tensor(up, dtype=torch.float64, device=HOST)
        right = torch.linalg.cross(forward, up_t)
        if right.norm() < 1e-9:
            raise ValueError("look_at: up is parallel to the viewing direction")
        right = right / right.norm()
        down = torch.linalg.cross(forward, right)
        R = torch.stack([right, down, forward])
        t = -R @ eye_t
        if not 0.0 < fov_deg < 180.0:
            raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
        fx = 0.5 * width / math.tan(math.radians(fov_deg) / 2.0)
        return Camera(R.float(), t.float(), fx, fx, width / 2.0, height / 2.0, width, height, name, near)


class View(NamedTuple):
    """A camera and the image it sees, the target a render of it is scored against: ``image`` [H, W, 3] float32 in
    [0, 1], the size of ``camera``; ``mask`` [H, W] bool, the object's own pixels (every pixel where no scene told
    them apart); ``name``, where the image came from ("" for a render)."""

    camera: Camera
    image: Tensor
    mask: Tensor
    name: str = ""


def near_for(radius: float) -> float:
    """The near plane of cameras placed around a scene of ``radius``."""
    return min(NEAR_PLANE, NEAR_SHARE * radius)


SPLAT_SIGMAS = 5.0


def scene_bounds(means: Tensor, scales: Tensor | None = None) -> tuple[Tensor, float]:
    """Robust centre (median) [3], on ``means``' device, and radius (95th percentile distance) of a point set [N, 3].

    With the Gaussians' log-scales [N, 3], the radius is at least ``SPLAT_SIGMAS`` of the median Gaussian's largest
    sigmas: a scene of one Gaussian, or of a few at one point, is framed whole rather than seen from inside its splat
    (a camera at the nearest of ``views.DISTANCES`` then sees 3.7 sigmas across half its frame)."""
    if means.shape[0] == 0:
        return torch.zeros(3, dtype=means.dtype, device=means.device), 1.0
    center = means.median(dim=0).values
    dist = (means - center).norm(dim=-1)
    radius = float(torch.quantile(dist.float(), 0.95)) if dist.numel() > 1 else 0.0
    if scales is not None:
        radius = max(radius, SPLAT_SIGMAS * float(scales.detach().max(dim=-1).values.median().exp()))
    # A point set of no size still gets cameras a float apart from its centre.
    return center, max(radius, 1e-6 * max(1.0, float(center.abs().max())))


def fibonacci_directions(count: int) -> Tensor:
    """``count`` unit vectors [count, 3] spread evenly over the sphere, on the host."""
    i = torch.arange(count, dtype=torch.float64, device=HOST) + 0.5
    z = 1.0 - 2.0 * i / count
    r = torch.sqrt(torch.clamp(1.0 - z * z, min=0.0))
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


def orbit_cameras(
    center: Tensor,
    radius: float,
    count: int,
    width: int = 256,
    height: int = 256,
    fov_deg: float = 50.0,
    margin: float = 1.15,
    up: tuple[float, float, float] = (0.0, 0.0, 1.0),
) -> list[Camera]:
    """``count`` cameras spread over a sphere around ``center`` [3], each framing a ball of ``radius``."""
    distance = margin * radius / math.sin(math.radians(fov_deg) / 2.0)
    center = center.to(HOST)
    up_t = torch.tensor(up, dtype=torch.float64, device=HOST)
    cams = []
    for i, d in enumerate(fibonacci_directions(count)):
        # Near the poles the world up is parallel to the view: use another up there.
        cam_up = up_t if abs(float(d @ up_t)) < 0.99 else up_t.new_tensor([0.0, 1.0, 0.0])
        eye = center.to(torch.float64) + distance * d
        cams.append(Camera.look_at(eye, center.to(torch.float64), cam_up, fov_deg, width, height,
                                   name=f"orbit_{i:03d}", near=near_for(radius)))  # fmt: skip
    return cams


def scene_cameras(
    means: Tensor, count: int, width: int = 256, height: int = 256, fov_deg: float = 50.0
) -> list[Camera]:
    """Cameras over the bounding sphere of a scene that came without images."""
    center, radius = scene_bounds(means.detach().cpu())
    return orbit_cameras(center, radius, count, width, height, fov_deg)


@dataclass(frozen=True)
class Focus:
    """What a set of cameras looks at: a ball, ``centre`` [3] on the cameras' device, ``radius`` in world units."""

    centre: Tensor
    radius: float

    def holds(self, means: Tensor) -> Tensor:
        """Indices [K] of the points ``means`` [N, 3] inside the ball, ascending, on ``means``' device."""
        centre = self.centre.to(device=means.device, dtype=means.dtype)
        return torch.nonzero((means - centre).norm(dim=1) <= self.radius)[:, 0]


def focus(cameras: Sequence[Camera]) -> Focus | None:
    """The object a capture's cameras look at: the point nearest all their optical axes (least squares) and the
    largest ball around it that the median camera frames whole (its depth times the tangent of its narrowest
    half-field). None for fewer than two cameras, for axes that do not cross (``CROSSING``) or a point behind them."""
    if len(cameras) < 2:
        return None
    R = torch.stack([c.R for c in cameras]).to(torch.float64)  # [C, 3, 3]
    t = torch.stack([c.t for c in cameras]).to(torch.float64)  # [C, 3]
    centres = -(R.transpose(1, 2) @ t[..., None])[..., 0]  # [C, 3]
    axes = R[:, 2]  # [C, 3]: each camera's z (forward) in world coordinates
    projectors = torch.eye(3, dtype=R.dtype, device=R.device) - axes[:, :, None] * axes[:, None, :]  # [C, 3, 3]
    mean = projectors.mean(dim=0)
    if float(torch.linalg.eigvalsh(mean)[0]) < CROSSING:
        return None
    point = torch.linalg.solve(mean, (projectors @ centres[..., None])[..., 0].mean(dim=0))
    depth = ((point - centres) * axes).sum(dim=1)  # [C]
    half = torch.tensor([min(min(c.cx, c.width - c.cx) / c.fx, min(c.cy, c.height - c.cy) / c.fy) for c in cameras],
                        dtype=R.dtype, device=R.device)  # fmt: skip
    radius = float((depth * half).median())
    if not (radius > 0 and math.isfinite(radius)):
        return None
    return Focus(point, radius)
