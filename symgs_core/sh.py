"""Real spherical harmonics with the basis and sign conventions of the original 3DGS code, and their reflection."""

from __future__ import annotations

import math
from functools import lru_cache

import torch
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_coeffs(degree: int) -> int:
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Tensor) -> Tensor:
    """Basis values [..., (degree+1)^2] at unit directions ``dirs`` [..., 3]."""
    if not 0 <= degree <= 3:
        raise ValueError(f"SH degree must be 0..3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [torch.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            C2[0] * x * y,
            C2[1] * y * z,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * x * z,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Raw SH value [N, 3] of ``coeffs`` [N, (deg+1)^2, 3] (DC first) along unit ``dirs`` [N, 3]."""
    degree = math.isqrt(coeffs.shape[-2]) - 1
    if num_coeffs(degree) != coeffs.shape[-2]:
        raise ValueError(f"coefficient count {coeffs.shape[-2]} is not a square")
    basis = sh_basis(degree, dirs)  # [N, M]
    return torch.einsum("nm,nmc->nc", basis, coeffs)


def sh_to_rgb(coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Colour [N, 3] as 3DGS computes it: max(SH + 0.5, 0)."""
    return torch.clamp_min(eval_sh(coeffs, dirs) + 0.5, 0.0)


def _fibonacci_sphere(n: int) -> Tensor:
    i = torch.arange(n, dtype=torch.float64, device="cpu") + 0.5
    z = 1.0 - 2.0 * i / n
    r = torch.sqrt(1.0 - z * z)
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


# 64 fixed sample directions: more than the 16 unknowns of degree 3, spread evenly so the solve is well conditioned.
_SAMPLES = 64


@lru_cache(maxsize=16)
def _sample_basis_pinv(degree: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """The sample directions [S, 3] and the pseudo-inverse of their basis [M, S], float64 on ``device``: solved once
    on the CPU, kept per device."""
    dirs = _fibonacci_sphere(_SAMPLES)
    return dirs.to(device), torch.linalg.pinv(sh_basis(degree, dirs)).to(device)


def sh_transform_matrix(matrix: Tensor, degree: int) -> Tensor:
    """Matrix T [(deg+1)^2, (deg+1)^2] with sum_j T[k, j] a_j the coefficients of d -> c(matrix @ d).

    ``matrix`` [3, 3] is orthogonal (a rotation or a reflection). Bands never mix. Exact up to float64 rounding
    because each band's span is closed under orthogonal maps; differentiable in ``matrix``.
    """
    dirs, pinv = _sample_basis_pinv(degree, matrix.device)
    m = matrix.to(torch.float64)
    mapped = dirs @ m.T  # rows: matrix @ d
    return pinv @ sh_basis(degree, mapped)


def reflect_sh_rest(sh_rest: Tensor, householder: Tensor) -> Tensor:
    """Reflected higher SH coefficients [N, K, 3] so that c'(d) = c(H d); the DC term is unchanged."""
    k = sh_rest.shape[1]
    if k == 0:
        return sh_rest
    degree = math.isqrt(k + 1) - 1
    t = sh_transform_matrix(householder, degree)[1:, 1:].to(sh_rest.dtype)
    return torch.einsum("kj,njc->nkc", t, sh_rest)
