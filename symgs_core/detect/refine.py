"""Continuous refinement of a plane, from the pairs that voted near its peak or from matched correspondences."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ..compiled import compiled


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
    for it in range(iters):
        # The window narrows from three cells to one: first towards the middle of the vote cloud, then onto its mode.
        shrink = max(1.0, 3.0 - 2.0 * it / max(iters - 1, 1))
        cos = dirs @ n
        aligned = dirs * torch.where(cos < 0, -1.0, 1.0)[:, None].to(dirs.dtype)
        angle = torch.acos(cos.abs().clamp(max=1.0))
        resid = mid @ n - g
        w = torch.exp(-0.5 * (angle / (shrink * angle_scale)) ** 2 - 0.5 * (resid / (shrink * offset_scale)) ** 2)
        if not float(w.sum()) > 0:
            break
        pulled = (w[:, None] * length[:, None] * aligned).sum(0)
        n = pulled / pulled.norm()
        g = float((w * (mid @ n)).sum() / w.sum())
    return n.cpu(), g


def _tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors [3] orthogonal to the unit vector ``n`` [3] and to each other."""
    helper = np.zeros(3)
    helper[int(np.abs(n).argmin())] = 1.0
    e1 = np.cross(n, helper)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(n, e1)


def fit_reflection(
    a: np.ndarray,
    b: np.ndarray,
    surface_normal: np.ndarray,
    flat: np.ndarray,
    weight: np.ndarray,
    normal: np.ndarray,
    offset: float,
) -> tuple[np.ndarray, float]:
    """One Gauss-Newton step of the plane that best maps points a [M, 3] onto their matches b [M, 3].

    Where the match lies on a surface (``flat`` [M] bool, unit ``surface_normal`` [M, 3]) only the distance along
    that normal counts (point-to-plane): sliding along the surface is free, so the fit is not held back by where the
    two independent samplings happened to put their Gaussians. Elsewhere the whole offset counts (point-to-point).
    The plane moves in its two tilt directions and its offset; ``weight`` [M] weighs the pairs. Returns the new unit
    normal [3] and offset (float64).
    """
    n = np.asarray(normal, dtype=np.float64)
    e1, e2 = _tangent_basis(n)
    lhs, rhs = np.zeros((3, 3)), np.zeros(3)
    _normal_equations(
        np.ascontiguousarray(a, dtype=np.float64),
        np.ascontiguousarray(b, dtype=np.float64),
        np.ascontiguousarray(surface_normal, dtype=np.float64),
        np.ascontiguousarray(flat, dtype=np.bool_),
        np.ascontiguousarray(weight, dtype=np.float64),
        np.stack([e1, e2, n]),
        float(offset),
        lhs,
        rhs,
    )
    lhs += 1e-9 * max(float(np.trace(lhs)), 1e-30) * np.eye(3)
    step = -np.linalg.solve(lhs, rhs)
    new_n = n + step[0] * e1 + step[1] * e2
    norm = float(np.linalg.norm(new_n))
    return new_n / norm, float((offset + step[2]) / norm)


@compiled
def _normal_equations(a, b, m, flat, weight, basis, offset, lhs, rhs):  # noqa: ANN001, ANN202
    """The Gauss-Newton system of ``fit_reflection`` accumulated into lhs [3, 3] and rhs [3] in one pass over the
    pairs (basis [3, 3]: rows e1, e2, n), instead of a dozen array-wide products, whose threaded BLAS stalls on a
    busy machine."""
    e1, e2, n = basis[0], basis[1], basis[2]
    cols = np.empty((3, 3))
    resid = np.empty(3)
    jac = np.empty(3)
    for r in range(a.shape[0]):
        d = a[r, 0] * n[0] + a[r, 1] * n[1] + a[r, 2] * n[2] - offset
        t1 = a[r, 0] * e1[0] + a[r, 1] * e1[1] + a[r, 2] * e1[2]
        t2 = a[r, 0] * e2[0] + a[r, 1] * e2[1] + a[r, 2] * e2[2]
        for c in range(3):
            resid[c] = a[r, c] - 2.0 * d * n[c] - b[r, c]
            # Derivatives of the reflected point a - 2 (n.a - g) n along the tilts e1, e2 and the offset g.
            cols[0, c] = -2.0 * (t1 * n[c] + d * e1[c])
            cols[1, c] = -2.0 * (t2 * n[c] + d * e2[c])
            cols[2, c] = 2.0 * n[c]
        w = weight[r]
        if flat[r]:  # point-to-plane: only the distance along the surface normal m counts
            res = m[r, 0] * resid[0] + m[r, 1] * resid[1] + m[r, 2] * resid[2]
            for p in range(3):
                jac[p] = m[r, 0] * cols[p, 0] + m[r, 1] * cols[p, 1] + m[r, 2] * cols[p, 2]
            for p in range(3):
                rhs[p] += w * jac[p] * res
                for q in range(3):
                    lhs[p, q] += w * jac[p] * jac[q]
        else:  # point-to-point
            for p in range(3):
                rhs[p] += w * (cols[p, 0] * resid[0] + cols[p, 1] * resid[1] + cols[p, 2] * resid[2])
                for q in range(3):
                    lhs[p, q] += w * (cols[p, 0] * cols[q, 0] + cols[p, 1] * cols[q, 1] + cols[p, 2] * cols[q, 2])
