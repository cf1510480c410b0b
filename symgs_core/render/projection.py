"""EWA projection of 3D Gaussians onto a pinhole camera, in plain PyTorch so autograd differentiates it."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..cameras import Camera
from ..scene import GaussianScene
from ..sh import num_coeffs, sh_to_rgb

NEAR_PLANE = 0.01
# Added to the 2D covariance's diagonal: every splat covers at least about a pixel (3DGS's low-pass filter).
LOW_PASS = 0.3
# The Jacobian is evaluated with x/z and y/z clamped to this multiple of the half field of view, as 3DGS does, so
# Gaussians far outside the view do not smear across the image.
FOV_CLAMP = 1.3


@dataclass
class Projection:
    """The Gaussians that may touch the image, front to back.

    index    [M]     their rows in the scene (int64)
    means2d  [M, 2]  pixel coordinates of the centres (pixel centres at +0.5)
    conics   [M, 3]  inverse 2D covariance (a, b, c)
    depths   [M]     camera-space z
    radii    [M]     3-sigma radius in pixels (whole numbers, no gradient)
    colors   [M, 3]  SH colour towards the camera
    opacity  [M]     activated opacity
    """

    index: Tensor
    means2d: Tensor
    conics: Tensor
    depths: Tensor
    radii: Tensor
    colors: Tensor
    opacity: Tensor


def quat_to_rotmat(quats: Tensor) -> Tensor:
    """Rotation matrices [N, 3, 3] of quaternions [N, 4] (w, x, y, z), normalised first."""
    w, x, y, z = torch.nn.functional.normalize(quats, dim=-1).unbind(-1)
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(-1, 3, 3)


def covariance3d(quats: Tensor, log_scales: Tensor) -> Tensor:
    """World covariances [N, 3, 3] = R S^2 R^T."""
    m = quat_to_rotmat(quats) * torch.exp(log_scales)[:, None, :]
    return m @ m.transpose(1, 2)


def project(scene: GaussianScene, camera: Camera, sh_degree: int) -> Projection:
    """Project ``scene`` into ``camera``; Gaussians behind the near plane or entirely off-screen are dropped."""
    dtype, device = scene.means.dtype, scene.means.device
    rot = camera.R.to(device=device, dtype=dtype)
    trans = camera.t.to(device=device, dtype=dtype)
    width, height = camera.width, camera.height

    depth_all = scene.means.detach() @ rot[2] + trans[2]
    index = torch.nonzero(depth_all > NEAR_PLANE).squeeze(1)
    means = scene.means[index]
    p = means @ rot.T + trans  # [F, 3]
    x, y, z = p.unbind(-1)

    lim_x = FOV_CLAMP * 0.5 * width / camera.fx
    lim_y = FOV_CLAMP * 0.5 * height / camera.fy
    tx = z * torch.clamp(x / z, -lim_x, lim_x)
    ty = z * torch.clamp(y / z, -lim_y, lim_y)
    zero = torch.zeros_like(z)
    jac = torch.stack(
        [camera.fx / z, zero, -camera.fx * tx / (z * z), zero, camera.fy / z, -camera.fy * ty / (z * z)], dim=-1
    ).reshape(-1, 2, 3)
    jw = jac @ rot  # [F, 2, 3]
    cov2d = jw @ covariance3d(scene.quats[index], scene.scales[index]) @ jw.transpose(1, 2)
    a = cov2d[:, 0, 0] + LOW_PASS
    b = cov2d[:, 0, 1]
    c = cov2d[:, 1, 1] + LOW_PASS
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    means2d = torch.stack([camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy], dim=-1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        lam = mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))
        radii = torch.ceil(3.0 * torch.sqrt(lam))
        u, v = means2d.unbind(-1)
        # Keep a Gaussian when some pixel centre j + 0.5 lies within its radius, in both axes.
        on_screen = (
            (torch.ceil(u - radii - 0.5) <= width - 1)
            & (torch.floor(u + radii - 0.5) >= 0)
            & (torch.ceil(v - radii - 0.5) <= height - 1)
            & (torch.floor(v + radii - 0.5) >= 0)
            & (det > 0)
        )
        keep = torch.nonzero(on_screen).squeeze(1)
        keep = keep[torch.argsort(z.detach()[keep], stable=True)]

    means_kept = means[keep]
    dirs = means_kept - camera.center.to(device=device, dtype=dtype)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    rows = index[keep]
    coeffs = torch.cat([scene.sh_dc[rows, None, :], scene.sh_rest[rows, : num_coeffs(sh_degree) - 1]], dim=1)
    return Projection(
        index=rows,
        means2d=means2d[keep],
        conics=conics[keep],
        depths=z[keep],
        radii=radii[keep],
        colors=sh_to_rgb(coeffs, dirs),
        opacity=torch.sigmoid(scene.opacities[rows]),
    )
