"""Continuous refinement of a plane, from the pairs that voted near its peak or from matched correspondences."""

from __future__ import annotations

import torch
from torch import Tensor


def refine_from_pairs(
    xi: Tensor, xj: Tensor, normal: Tensor, offset: float, angle_scale: float, offset_scale: float, iters: int
) -> tuple[Tensor, float]:
    """Mean shift of the plane over the bisecting planes of pairs (xi [P, 3], xj [P, 3]).

    Each pair proposes the normal (xi - xj) / |xi - xj| and passes through its midpoint. Weights fall off with the
    angle to the current normal (scale ``angle_scale`` rad) and with the midpoint's distance to the current plane
    (``offset_scale``); long pairs, whose direction is least disturbed by positional noise, weigh more. Returns the
    refined unit normal [3] (float64) and offset; the input plane when no pair supports it.
    """
    n = normal.to(torch.float64)
    g = float(offset)
    if xi.shape[0] == 0:
        return n, g
    diff = (xi - xj).to(torch.float64)
    length = diff.norm(dim=1).clamp_min(1e-12)
    dirs = diff / length[:, None]
    mid = ((xi + xj) / 2).to(torch.float64)
    n = n.to(dirs.device)
    for _ in range(iters):
        cos = dirs @ n
        aligned = dirs * torch.where(cos < 0, -1.0, 1.0)[:, None].to(dirs.dtype)
        angle = torch.acos(cos.abs().clamp(max=1.0))
        resid = mid @ n - g
        w = torch.exp(-0.5 * (angle / angle_scale) ** 2 - 0.5 * (resid / offset_scale) ** 2)
        if not float(w.sum()) > 0:
            break
        pulled = (w[:, None] * length[:, None] * aligned).sum(0)
        n = pulled / pulled.norm()
        g = float((w * (mid @ n)).sum() / w.sum())
    return n.cpu(), g


def _tangent_basis(n: Tensor) -> tuple[Tensor, Tensor]:
    """Two unit vectors [3] orthogonal to the unit vector ``n`` [3] and to each other."""
    helper = torch.zeros_like(n)
    helper[int(n.abs().argmin())] = 1.0
    e1 = torch.linalg.cross(n, helper)
    e1 = e1 / e1.norm()
    return e1, torch.linalg.cross(n, e1)


def fit_reflection(
    a: Tensor, b: Tensor, surface_normal: Tensor, flat: Tensor, weight: Tensor, normal: Tensor, offset: float
) -> tuple[Tensor, float]:
    """One Gauss-Newton step of the plane that best maps points a [M, 3] onto their matches b [M, 3].

    Where the match lies on a surface (``flat`` [M] bool, unit ``surface_normal`` [M, 3]) only the distance along
    that normal counts (point-to-plane): sliding along the surface is free, so the fit is not held back by where the
    two independent samplings happened to put their Gaussians. Elsewhere the whole offset counts (point-to-point).
    The plane moves in its two tilt directions and its offset. Returns the new unit normal [3] and offset (float64).
    """
    a, b = a.to(torch.float64), b.to(torch.float64)
    m, w = surface_normal.to(torch.float64), weight.to(torch.float64)
    n = normal.to(torch.float64)
    e1, e2 = _tangent_basis(n)
    d = a @ n - offset  # [M]
    resid = a - 2.0 * d[:, None] * n - b  # [M, 3]
    # Derivatives of the reflected point a - 2 (n.a - g) n along e1, e2 (tilts) and g (offset): [M, 3, 3].
    tilt = [-2.0 * ((a @ e)[:, None] * n + d[:, None] * e) for e in (e1, e2)]
    jac = torch.stack([*tilt, (2.0 * n).expand_as(a)], dim=-1)
    f = flat[:, None].to(torch.float64)
    # Flat matches: one row m . resid; others: the three rows of resid. Rows of a non-flat pair's m-projection
    # and of a flat pair's full residual are zeroed by ``f``.
    r_plane = (m * resid).sum(-1) * f[:, 0]
    j_plane = torch.einsum("mi,mij->mj", m, jac) * f
    r_point = resid * (1.0 - f)
    j_point = jac * (1.0 - f)[:, :, None]
    lhs = torch.einsum("m,mi,mj->ij", w, j_plane, j_plane) + torch.einsum("m,mki,mkj->ij", w, j_point, j_point)
    rhs = torch.einsum("m,mi,m->i", w, j_plane, r_plane) + torch.einsum("m,mki,mk->i", w, j_point, r_point)
    lhs = lhs + 1e-9 * torch.eye(3, dtype=lhs.dtype) * float(lhs.diagonal().sum().clamp_min(1e-30))
    step = -torch.linalg.solve(lhs, rhs)
    new_n = n + step[0] * e1 + step[1] * e2
    norm = new_n.norm()
    return new_n / norm, float((offset + step[2]) / norm)
