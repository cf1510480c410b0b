"""EWA projection of 3D Gaussians onto a pinhole camera, in plain PyTorch so autograd differentiates it.

Every Gaussian is projected (no gathers: their backward is a slow scatter on the CPU); those behind the near plane get
radius 0 and finite placeholder values, and the rasterizer skips them along with those that land off-screen. The
2x3 and 3x3 products are written out elementwise, which is several times faster than batched 3x3 matmuls.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from ..cameras import Camera
from ..scene import GaussianScene
from ..sh import num_coeffs, sh_to_rgb

# Added to the 2D covariance's diagonal: every splat covers at least about a pixel (3DGS's low-pass filter).
LOW_PASS = 0.3
# The Jacobian is evaluated with x/z and y/z clamped to this multiple of the half field of view, as 3DGS does, so
# Gaussians far outside the view do not smear across the image.
FOV_CLAMP = 1.3


@dataclass
class Projection:
    """Every scene Gaussian as seen by the camera.

    means2d  [N, 2]  pixel coordinates of the centres (pixel centres at +0.5)
    conics   [N, 3]  inverse 2D covariance (a, b, c): power = -0.5 (a dx^2 + c dy^2) - b dx dy
    depths   [N]     camera-space z
    radii    [N]     3-sigma radius in pixels (whole numbers, no gradient); 0 behind the near plane or non-finite
    colors   [N, 3]  SH colour towards the camera
    opacity  [N]     activated opacity
    """

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


def project(scene: GaussianScene, camera: Camera, sh_degree: int) -> Projection:
    """Project every Gaussian of ``scene`` into ``camera`` (EWA splatting with 3DGS's conventions)."""
    dtype, device = scene.means.dtype, scene.means.device
    rot = camera.R.to(device=device, dtype=dtype)
    p = scene.means @ rot.T + camera.t.to(device=device, dtype=dtype)  # [N, 3] camera space
    x, y, z = p.unbind(-1)
    in_front = z.detach() > camera.near
    z = torch.where(in_front, z, torch.ones_like(z))  # placeholder keeps culled rows finite in both passes

    lim_x = FOV_CLAMP * 0.5 * camera.width / camera.fx
    lim_y = FOV_CLAMP * 0.5 * camera.height / camera.fy
    j00 = camera.fx / z
    j02 = -camera.fx * torch.clamp(x / z, -lim_x, lim_x) / z
    j11 = camera.fy / z
    j12 = -camera.fy * torch.clamp(y / z, -lim_y, lim_y) / z
    # Rows of J R_cam [N, 3], then of (J R_cam)(R_g S) [N, 3]: cov2d = P P^T.
    jw0 = j00[:, None] * rot[0] + j02[:, None] * rot[2]
    jw1 = j11[:, None] * rot[1] + j12[:, None] * rot[2]
    m = quat_to_rotmat(scene.quats) * torch.exp(scene.scales)[:, None, :]  # R_g S [N, 3, 3]
    p0 = (jw0[:, :, None] * m).sum(1)
    p1 = (jw1[:, :, None] * m).sum(1)
    a = (p0 * p0).sum(-1) + LOW_PASS
    b = (p0 * p1).sum(-1)
    c = (p1 * p1).sum(-1) + LOW_PASS
    det = a * c - b * b
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)
    means2d = torch.stack([camera.fx * x / z + camera.cx, camera.fy * y / z + camera.cy], dim=-1)

    with torch.no_grad():
        mid = 0.5 * (a + c)
        radii = torch.ceil(3.0 * torch.sqrt(mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))))
        # Non-finite rows (NaN means, infinite scales) are culled rather than allowed to poison the image.
        valid = in_front & (det > 0) & torch.isfinite(radii) & torch.isfinite(means2d).all(-1)
        radii = torch.where(valid, radii, torch.zeros_like(radii))

    dirs = scene.means - camera.center.to(device=device, dtype=dtype)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    coeffs = torch.cat([scene.sh_dc[:, None, :], scene.sh_rest[:, : num_coeffs(sh_degree) - 1]], dim=1)
    return Projection(
        means2d=means2d,
        conics=conics,
        depths=z,
        radii=radii,
        colors=sh_to_rgb(coeffs, dirs),
        opacity=torch.sigmoid(scene.opacities),
    )
