"""The EWA projection of ``projection.project`` as one compiled pass over the Gaussians: no temporaries per step,
and rows off-screen skip their colour (no render uses it, and their gradient is zero). Its backward is
``_project_grad``.

It follows ``project`` operation for operation, in float32 as the tensors are, so the two agree to rounding (a
test holds them together); ``project`` stays the reference.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..sh import C0, C1, C2, C3
from .projection import FOV_CLAMP, LOW_PASS

_C2 = np.array(C2, dtype=np.float32)
_C3 = np.array(C3, dtype=np.float32)


@njit(cache=True, nogil=True, parallel=True, fastmath=False)
def project_kernel(
    means: np.ndarray,  # [N, 3] f32
    quats: np.ndarray,  # [N, 4]
    scales: np.ndarray,  # [N, 3] log
    opacities: np.ndarray,  # [N] logits
    dc: np.ndarray,  # [N, 3] SH DC
    rest: np.ndarray,  # [N, K, 3] higher SH
    m: int,  # SH coefficients used, DC included: (degree + 1)^2
    rot: np.ndarray,  # [3, 3] world to camera
    trans: np.ndarray,  # [3]
    center: np.ndarray,  # [3] camera centre
    fx: np.float32, fy: np.float32, cx: np.float32, cy: np.float32,  # float32, as the tensors are
    width: int, height: int, near: float, c2: np.ndarray, c3: np.ndarray,
    means2d: np.ndarray, conics: np.ndarray, depths: np.ndarray, radii: np.ndarray, colors: np.ndarray,
    opacity: np.ndarray,
) -> None:  # fmt: skip
    n = means.shape[0]
    lim_x = np.float32(FOV_CLAMP * 0.5 * width / fx)
    lim_y = np.float32(FOV_CLAMP * 0.5 * height / fy)
    for i in prange(n):
        x = rot[0, 0] * means[i, 0] + rot[0, 1] * means[i, 1] + rot[0, 2] * means[i, 2] + trans[0]
        y = rot[1, 0] * means[i, 0] + rot[1, 1] * means[i, 1] + rot[1, 2] * means[i, 2] + trans[1]
        z = rot[2, 0] * means[i, 0] + rot[2, 1] * means[i, 1] + rot[2, 2] * means[i, 2] + trans[2]
        in_front = z > near
        if not in_front:
            z = np.float32(1.0)
        depths[i] = z
        opacity[i] = 1.0 / (1.0 + math.exp(-opacities[i]))
        j00 = fx / z
        j02 = -fx * min(max(x / z, -lim_x), lim_x) / z
        j11 = fy / z
        j12 = -fy * min(max(y / z, -lim_y), lim_y) / z
        jw00 = j00 * rot[0, 0] + j02 * rot[2, 0]
        jw01 = j00 * rot[0, 1] + j02 * rot[2, 1]
        jw02 = j00 * rot[0, 2] + j02 * rot[2, 2]
        jw10 = j11 * rot[1, 0] + j12 * rot[2, 0]
        jw11 = j11 * rot[1, 1] + j12 * rot[2, 1]
        jw12 = j11 * rot[1, 2] + j12 * rot[2, 2]
        qw, qx, qy, qz = quats[i, 0], quats[i, 1], quats[i, 2], quats[i, 3]
        norm = max(math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz), 1e-12)
        qw, qx, qy, qz = qw / norm, qx / norm, qy / norm, qz / norm
        s0, s1, s2 = math.exp(scales[i, 0]), math.exp(scales[i, 1]), math.exp(scales[i, 2])
        # R_g S, column k scaled by s_k.
        r00 = (1 - 2 * (qy * qy + qz * qz)) * s0
        r01 = 2 * (qx * qy - qw * qz) * s1
        r02 = 2 * (qx * qz + qw * qy) * s2
        r10 = 2 * (qx * qy + qw * qz) * s0
        r11 = (1 - 2 * (qx * qx + qz * qz)) * s1
        r12 = 2 * (qy * qz - qw * qx) * s2
        r20 = 2 * (qx * qz - qw * qy) * s0
        r21 = 2 * (qy * qz + qw * qx) * s1
        r22 = (1 - 2 * (qx * qx + qy * qy)) * s2
        p00 = jw00 * r00 + jw01 * r10 + jw02 * r20
        p01 = jw00 * r01 + jw01 * r11 + jw02 * r21
        p02 = jw00 * r02 + jw01 * r12 + jw02 * r22
        p10 = jw10 * r00 + jw11 * r10 + jw12 * r20
        p11 = jw10 * r01 + jw11 * r11 + jw12 * r21
        p12 = jw10 * r02 + jw11 * r12 + jw12 * r22
        a = p00 * p00 + p01 * p01 + p02 * p02 + LOW_PASS
        b = p00 * p10 + p01 * p11 + p02 * p12
        c = p10 * p10 + p11 * p11 + p12 * p12 + LOW_PASS
        det = a * c - b * b
        conics[i, 0] = c / det
        conics[i, 1] = -b / det
        conics[i, 2] = a / det
        u = fx * x / z + cx
        v = fy * y / z + cy
        means2d[i, 0] = u
        means2d[i, 1] = v
        mid = 0.5 * (a + c)
        radius = math.ceil(3.0 * math.sqrt(mid + math.sqrt(max(mid * mid - det, 0.1))))
        valid = in_front and det > 0 and math.isfinite(radius) and math.isfinite(u) and math.isfinite(v)
        radii[i] = radius if valid else 0.0
        # The colour of a Gaussian that lands off-screen is never used: skip its SH.
        if not valid or u + radius < 0 or v + radius < 0 or u - radius > width or v - radius > height:
            colors[i, 0] = colors[i, 1] = colors[i, 2] = 0.0
            continue
        dx, dy, dz = means[i, 0] - center[0], means[i, 1] - center[1], means[i, 2] - center[2]
        dn = max(math.sqrt(dx * dx + dy * dy + dz * dz), 1e-12)
        dx, dy, dz = dx / dn, dy / dn, dz / dn
        for ch in range(3):
            val = C0 * dc[i, ch]
            if m > 1:
                val += -C1 * dy * rest[i, 0, ch] + C1 * dz * rest[i, 1, ch] - C1 * dx * rest[i, 2, ch]
            if m > 4:
                xx, yy, zz = dx * dx, dy * dy, dz * dz
                val += (c2[0] * dx * dy * rest[i, 3, ch] + c2[1] * dy * dz * rest[i, 4, ch]
                        + c2[2] * (2.0 * zz - xx - yy) * rest[i, 5, ch] + c2[3] * dx * dz * rest[i, 6, ch]
                        + c2[4] * (xx - yy) * rest[i, 7, ch])  # fmt: skip
                if m > 9:
                    val += (c3[0] * dy * (3.0 * xx - yy) * rest[i, 8, ch] + c3[1] * dx * dy * dz * rest[i, 9, ch]
                            + c3[2] * dy * (4.0 * zz - xx - yy) * rest[i, 10, ch]
                            + c3[3] * dz * (2.0 * zz - 3.0 * xx - 3.0 * yy) * rest[i, 11, ch]
                            + c3[4] * dx * (4.0 * zz - xx - yy) * rest[i, 12, ch]
                            + c3[5] * dz * (xx - yy) * rest[i, 13, ch]
                            + c3[6] * dx * (xx - 3.0 * yy) * rest[i, 14, ch])  # fmt: skip
            colors[i, ch] = max(val + 0.5, 0.0)


def project_fast(means, quats, scales, opacities, dc, rest, degree, camera):  # noqa: ANN001, ANN201 - arrays, a Camera
    """``project``'s outputs as numpy float32 arrays (means2d, conics, depths, radii, colors, opacity)."""
    n = len(means)
    f32 = np.float32
    outs = (np.empty((n, 2), f32), np.empty((n, 3), f32), np.empty(n, f32), np.empty(n, f32), np.empty((n, 3), f32),
            np.empty(n, f32))  # fmt: skip
    rot = np.ascontiguousarray(camera.R.detach().cpu().numpy(), dtype=f32)
    trans = np.ascontiguousarray(camera.t.detach().cpu().numpy(), dtype=f32)
    center = np.ascontiguousarray(camera.center.detach().cpu().numpy(), dtype=f32)
    project_kernel(means, quats, scales, opacities, dc, rest, (degree + 1) ** 2, rot, trans, center, f32(camera.fx),
                   f32(camera.fy),
                   f32(camera.cx), f32(camera.cy), camera.width, camera.height, float(camera.near), _C2, _C3,
                   *outs)  # fmt: skip
    return outs

