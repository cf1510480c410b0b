"""Dense all-pairs Gaussian renderer in plain PyTorch autograd: the correctness oracle for the tile rasterizer.

Every pixel meets every Gaussian; no tiles, no binning, no hand-written gradients. It follows the same rules as the
product (3DGS semantics) but is written independently from them:
  EWA projection, Jacobian with x/z and y/z clamped to 1.3 x the half field of view, +0.3 on the 2D diagonal,
  radius = ceil(3 sqrt(lambda_max)) with 3DGS's eigenvalue bound, near plane z > 0.01;
  a pixel centre p meets a Gaussian when |p - mean2d| <= radius in x and in y;
  alpha = min(0.99, opacity exp(-0.5 d^T conic d)), skipped below 1/255;
  front to back by depth, stopping before the Gaussian that would take the transmittance below 1e-4.
Too slow for real images (it is O(pixels x Gaussians)); for tests only.
"""

from __future__ import annotations

import torch
from torch import Tensor

from symgs_core.cameras import Camera
from symgs_core.scene import GaussianScene
from symgs_core.sh import sh_to_rgb


def _rotation(quats: Tensor) -> Tensor:
    """R = (w^2 - v.v) I + 2 v v^T + 2 w [v]x for unit quaternions, [N, 3, 3]."""
    q = quats / quats.norm(dim=-1, keepdim=True)
    w, v = q[:, 0], q[:, 1:]
    eye = torch.eye(3, dtype=q.dtype).expand(len(q), 3, 3)
    zero = torch.zeros_like(w)
    cross = torch.stack(
        [zero, -v[:, 2], v[:, 1], v[:, 2], zero, -v[:, 0], -v[:, 1], v[:, 0], zero], dim=-1
    ).reshape(-1, 3, 3)
    outer = v[:, :, None] * v[:, None, :]
    return (w * w - (v * v).sum(-1))[:, None, None] * eye + 2 * outer + 2 * w[:, None, None] * cross


def dense_render(
    scene: GaussianScene, camera: Camera, background: Tensor, sh_degree: int | None = None
) -> tuple[Tensor, Tensor, Tensor, dict[str, int]]:
    """Image [H, W, 3] (clamped to [0, 1]), alpha [H, W], expected depth [H, W], and counts of the rules that fired."""
    dtype = scene.means.dtype
    degree = scene.sh_degree if sh_degree is None else sh_degree
    rot_c = camera.R.to(dtype)
    t_c = camera.t.to(dtype)
    fx, fy, cx, cy, w_img, h_img = camera.fx, camera.fy, camera.cx, camera.cy, camera.width, camera.height

    p = scene.means @ rot_c.T + t_c
    z = p[:, 2]
    in_front = z > 0.01
    z_safe = torch.where(in_front, z, torch.ones_like(z))
    xz = torch.clamp(p[:, 0] / z_safe, -1.3 * w_img / (2 * fx), 1.3 * w_img / (2 * fx))
    yz = torch.clamp(p[:, 1] / z_safe, -1.3 * h_img / (2 * fy), 1.3 * h_img / (2 * fy))
    jac = torch.zeros(len(z), 2, 3, dtype=dtype)
    jac[:, 0, 0] = fx / z_safe
    jac[:, 0, 2] = -fx * xz / z_safe
    jac[:, 1, 1] = fy / z_safe
    jac[:, 1, 2] = -fy * yz / z_safe
    rot_g = _rotation(scene.quats)
    sigma = rot_g @ torch.diag_embed(torch.exp(2 * scene.scales)) @ rot_g.transpose(1, 2)
    t_mat = jac @ rot_c
    cov2d = t_mat @ sigma @ t_mat.transpose(1, 2) + 0.3 * torch.eye(2, dtype=dtype)
    conic = torch.linalg.inv(cov2d)  # [N, 2, 2]
    mean2d = torch.stack([fx * p[:, 0] / z_safe + cx, fy * p[:, 1] / z_safe + cy], dim=-1)

    det = torch.linalg.det(cov2d.detach())
    mid = 0.5 * (cov2d[:, 0, 0] + cov2d[:, 1, 1]).detach()
    radius = torch.ceil(3 * torch.sqrt(mid + torch.sqrt(torch.clamp_min(mid * mid - det, 0.1))))

    dirs = scene.means - camera.center.to(dtype)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    coeffs = scene.sh_coeffs()[:, : (degree + 1) ** 2]
    color = sh_to_rgb(coeffs, dirs)
    opacity = torch.sigmoid(scene.opacities)

    order = torch.argsort(torch.where(in_front, z, torch.inf).detach(), stable=True)
    ys, xs = torch.meshgrid(torch.arange(h_img, dtype=dtype), torch.arange(w_img, dtype=dtype), indexing="ij")
    pix = torch.stack([xs.flatten() + 0.5, ys.flatten() + 0.5], dim=-1)  # [P, 2]
    d = mean2d[order][None, :, :] - pix[:, None, :]  # [P, N, 2]
    power = -0.5 * torch.einsum("pni,nij,pnj->pn", d, conic[order], d)
    raw = opacity[order][None, :] * torch.exp(power)
    alpha = torch.clamp(raw, max=0.99)
    inside = (d.detach().abs() <= radius[order][None, :, None]).all(-1) & in_front[order][None, :]
    used = inside & (alpha.detach() >= 1 / 255)
    alpha = torch.where(used, alpha, torch.zeros_like(alpha))
    reached = torch.cumprod(1 - alpha.detach(), dim=-1) >= 1e-4
    alpha = torch.where(reached, alpha, torch.zeros_like(alpha))
    trans = torch.cumprod(torch.cat([torch.ones_like(alpha[:, :1]), 1 - alpha[:, :-1]], dim=-1), dim=-1)
    weight = alpha * trans  # [P, N]
    t_final = trans[:, -1] * (1 - alpha[:, -1]) if alpha.shape[1] else torch.ones(len(pix), dtype=dtype)

    rgb = weight @ color[order] + t_final[:, None] * background.to(dtype)
    acc_alpha = 1 - t_final
    depth = (weight @ z[order]) / acc_alpha.clamp_min(1e-10)
    counts = {
        "clamped": int((used & (raw.detach() > 0.99)).sum()),
        "stopped_pixels": int((used & ~reached).any(-1).sum()),
        "behind_camera": int((~in_front).sum()),
        "pairs": int((used & reached).sum()),
    }
    return (
        rgb.reshape(h_img, w_img, 3).clamp(0, 1),
        acc_alpha.reshape(h_img, w_img),
        depth.reshape(h_img, w_img),
        counts,
    )
