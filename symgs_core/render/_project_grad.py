"""The backward pass of ``projection.project`` as one compiled pass over the Gaussians.

Autograd through ``project`` builds some sixty [N]-sized temporaries per view and walks them back one kernel at a
time; at a million Gaussians that was about 0.75 s of each view's 1.1-1.5 s in the codec's sensitivity pass. Each
Gaussian's projection depends on its own attributes only, so its gradient is a closed form per row, computed here in
float64 from the float32 inputs (the forward is ``_project_kernel``). It follows ``project`` branch for branch: the
clamped Jacobian passes no gradient outside its limits, a Gaussian behind the near plane has a constant depth, a
colour clamped at zero passes none. A test holds it to autograd through ``project`` in float64.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..sh import C0, C1, C2, C3
from .projection import FOV_CLAMP, LOW_PASS

_C2 = np.array(C2, dtype=np.float64)
_C3 = np.array(C3, dtype=np.float64)


@njit(cache=True, nogil=True, fastmath=False)
def _sh_basis(x, y, z, c2, c3):  # noqa: ANN001, ANN202
    """The 15 higher SH basis functions (degrees 1-3, in ``sh_rest``'s order) at the unit direction (x, y, z); a
    lower degree uses the first (degree + 1)^2 - 1."""
    xx, yy, zz = x * x, y * y, z * z
    return (-C1 * y, C1 * z, -C1 * x,
            c2[0] * x * y, c2[1] * y * z, c2[2] * (2.0 * zz - xx - yy), c2[3] * x * z, c2[4] * (xx - yy),
            c3[0] * y * (3.0 * xx - yy), c3[1] * x * y * z, c3[2] * y * (4.0 * zz - xx - yy),
            c3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy), c3[4] * x * (4.0 * zz - xx - yy), c3[5] * z * (xx - yy),
            c3[6] * x * (xx - 3.0 * yy))  # fmt: skip


@njit(cache=True, nogil=True, fastmath=False)
def _sh_direction_grad(x, y, z, rest, i, ch, m, c2, c3):  # noqa: ANN001, ANN202
    """The gradient, with respect to the unit direction (x, y, z), of channel ``ch`` of Gaussian ``i``'s higher SH
    (``m`` coefficients used, DC included): the derivatives of ``_sh_basis`` weighted by the coefficients."""
    gx = gy = gz = 0.0
    if m > 1:
        r0, r1, r2 = rest[i, 0, ch], rest[i, 1, ch], rest[i, 2, ch]
        gx += -C1 * r2
        gy += -C1 * r0
        gz += C1 * r1
    if m > 4:
        xx, yy, zz = x * x, y * y, z * z
        r0, r1, r2, r3, r4 = rest[i, 3, ch], rest[i, 4, ch], rest[i, 5, ch], rest[i, 6, ch], rest[i, 7, ch]
        gx += c2[0] * y * r0 - 2.0 * c2[2] * x * r2 + c2[3] * z * r3 + 2.0 * c2[4] * x * r4
        gy += c2[0] * x * r0 + c2[1] * z * r1 - 2.0 * c2[2] * y * r2 - 2.0 * c2[4] * y * r4
        gz += c2[1] * y * r1 + 4.0 * c2[2] * z * r2 + c2[3] * x * r3
        if m > 9:
            r0, r1, r2, r3 = rest[i, 8, ch], rest[i, 9, ch], rest[i, 10, ch], rest[i, 11, ch]
            r4, r5, r6 = rest[i, 12, ch], rest[i, 13, ch], rest[i, 14, ch]
            gx += (6.0 * c3[0] * x * y * r0 + c3[1] * y * z * r1 - 2.0 * c3[2] * x * y * r2 - 6.0 * c3[3] * x * z * r3
                   + c3[4] * (4.0 * zz - 3.0 * xx - yy) * r4 + 2.0 * c3[5] * x * z * r5
                   + 3.0 * c3[6] * (xx - yy) * r6)  # fmt: skip
            gy += (3.0 * c3[0] * (xx - yy) * r0 + c3[1] * x * z * r1 + c3[2] * (4.0 * zz - xx - 3.0 * yy) * r2
                   - 6.0 * c3[3] * y * z * r3 - 2.0 * c3[4] * x * y * r4 - 2.0 * c3[5] * y * z * r5
                   - 6.0 * c3[6] * x * y * r6)  # fmt: skip
            gz += (c3[1] * x * y * r1 + 8.0 * c3[2] * y * z * r2 + c3[3] * (6.0 * zz - 3.0 * xx - 3.0 * yy) * r3
                   + 8.0 * c3[4] * x * z * r4 + c3[5] * (xx - yy) * r5)  # fmt: skip
    return gx, gy, gz


@njit(cache=True, nogil=True)
def _no_gradient(i, g_means2d, g_conics, g_depths, g_colors, g_opacity):  # noqa: ANN001, ANN202
    return (g_means2d[i, 0] == 0.0 and g_means2d[i, 1] == 0.0 and g_conics[i, 0] == 0.0 and g_conics[i, 1] == 0.0
            and g_conics[i, 2] == 0.0 and g_depths[i] == 0.0 and g_colors[i, 0] == 0.0 and g_colors[i, 1] == 0.0
            and g_colors[i, 2] == 0.0 and g_opacity[i] == 0.0)  # fmt: skip


@njit(cache=True, nogil=True)
def _zero(i, out_means, out_quats, out_scales, out_opacities, out_dc, out_rest):  # noqa: ANN001, ANN202
    out_means[i, :] = 0.0
    out_quats[i, :] = 0.0
    out_scales[i, :] = 0.0
    out_opacities[i] = 0.0
    out_dc[i, :] = 0.0
    out_rest[i, :, :] = 0.0


@njit(cache=True, nogil=True, parallel=True, fastmath=False)
def project_backward(
    means: np.ndarray,  # [N, 3] f32, the forward's inputs
    quats: np.ndarray,  # [N, 4]
    scales: np.ndarray,  # [N, 3] log
    opacities: np.ndarray,  # [N] logits
    dc: np.ndarray,  # [N, 3]
    rest: np.ndarray,  # [N, K, 3]
    m: int,  # SH coefficients used, DC included
    rot: np.ndarray,  # [3, 3] world to camera, float64
    trans: np.ndarray,  # [3]
    center: np.ndarray,  # [3]
    fx: float, fy: float, width: int, height: int, near: float, c2: np.ndarray, c3: np.ndarray,
    g_means2d: np.ndarray, g_conics: np.ndarray, g_depths: np.ndarray, g_colors: np.ndarray,  # the outputs' grads
    g_opacity: np.ndarray,
    out_means: np.ndarray, out_quats: np.ndarray, out_scales: np.ndarray, out_opacities: np.ndarray,  # f32, written
    out_dc: np.ndarray, out_rest: np.ndarray,
) -> None:  # fmt: skip
    n = means.shape[0]
    lim_x = FOV_CLAMP * 0.5 * width / fx
    lim_y = FOV_CLAMP * 0.5 * height / fy
    for i in prange(n):
        if _no_gradient(i, g_means2d, g_conics, g_depths, g_colors, g_opacity):
            # Gaussians no pixel took (culled, or behind what saturated): 30-90% of a 1M-Gaussian view's.
            _zero(i, out_means, out_quats, out_scales, out_opacities, out_dc, out_rest)
            continue
        s = 1.0 / (1.0 + math.exp(-float(opacities[i])))
        out_opacities[i] = g_opacity[i] * s * (1.0 - s)

        # Colour: max(C0 dc + SH(d) + 0.5, 0), d the unit direction from the camera centre.
        dx, dy, dz = means[i, 0] - center[0], means[i, 1] - center[1], means[i, 2] - center[2]
        norm = math.sqrt(dx * dx + dy * dy + dz * dz)
        dn = max(norm, 1e-12)
        dx, dy, dz = dx / dn, dy / dn, dz / dn
        basis = _sh_basis(dx, dy, dz, c2, c3)
        gdx = gdy = gdz = 0.0
        for ch in range(3):
            val = C0 * dc[i, ch]
            for k in range(m - 1):
                val += basis[k] * rest[i, k, ch]
            g = g_colors[i, ch] if val + 0.5 >= 0.0 else 0.0
            out_dc[i, ch] = C0 * g
            for k in range(out_rest.shape[1]):  # bands above the degree rendered get none
                out_rest[i, k, ch] = basis[k] * g if k < m - 1 else 0.0
            sx, sy, sz = _sh_direction_grad(dx, dy, dz, rest, i, ch, m, c2, c3)
            gdx, gdy, gdz = gdx + g * sx, gdy + g * sy, gdz + g * sz
        gmx = gmy = gmz = 0.0
        if norm > 1e-12:
            along = dx * gdx + dy * gdy + dz * gdz
            gmx, gmy, gmz = (gdx - dx * along) / norm, (gdy - dy * along) / norm, (gdz - dz * along) / norm

        # Camera space; behind the near plane z is the constant 1.
        x = rot[0, 0] * means[i, 0] + rot[0, 1] * means[i, 1] + rot[0, 2] * means[i, 2] + trans[0]
        y = rot[1, 0] * means[i, 0] + rot[1, 1] * means[i, 1] + rot[1, 2] * means[i, 2] + trans[1]
        z = rot[2, 0] * means[i, 0] + rot[2, 1] * means[i, 1] + rot[2, 2] * means[i, 2] + trans[2]
        in_front = z > near
        if not in_front:
            z = 1.0
        zz = z * z
        gx = g_means2d[i, 0] * fx / z
        gy = g_means2d[i, 1] * fy / z
        gz = g_depths[i] - (g_means2d[i, 0] * fx * x + g_means2d[i, 1] * fy * y) / zz

        # The Jacobian's rows times R_cam: jw0 = j00 R_cam[0] + j02 R_cam[2], jw1 = j11 R_cam[1] + j12 R_cam[2].
        tx, ty = x / z, y / z
        ctx, cty = min(max(tx, -lim_x), lim_x), min(max(ty, -lim_y), lim_y)
        j00, j02, j11, j12 = fx / z, -fx * ctx / z, fy / z, -fy * cty / z
        u0, u1, u2 = (j00 * rot[0, 0] + j02 * rot[2, 0], j00 * rot[0, 1] + j02 * rot[2, 1],
                      j00 * rot[0, 2] + j02 * rot[2, 2])  # fmt: skip
        v0, v1, v2 = (j11 * rot[1, 0] + j12 * rot[2, 0], j11 * rot[1, 1] + j12 * rot[2, 1],
                      j11 * rot[1, 2] + j12 * rot[2, 2])  # fmt: skip
        # R_g of the normalised quaternion, its columns scaled: M = R_g S.
        qw, qx, qy, qz = float(quats[i, 0]), float(quats[i, 1]), float(quats[i, 2]), float(quats[i, 3])
        qn = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
        qd = max(qn, 1e-12)
        w, a, b, c = qw / qd, qx / qd, qy / qd, qz / qd
        r00, r01, r02 = 1 - 2 * (b * b + c * c), 2 * (a * b - w * c), 2 * (a * c + w * b)
        r10, r11, r12 = 2 * (a * b + w * c), 1 - 2 * (a * a + c * c), 2 * (b * c - w * a)
        r20, r21, r22 = 2 * (a * c - w * b), 2 * (b * c + w * a), 1 - 2 * (a * a + b * b)
        s0, s1, s2 = math.exp(float(scales[i, 0])), math.exp(float(scales[i, 1])), math.exp(float(scales[i, 2]))
        # Columns of R_g^T jw, then p = that scaled: p0 = jw0^T M, p1 = jw1^T M.
        t0, t1, t2 = u0 * r00 + u1 * r10 + u2 * r20, u0 * r01 + u1 * r11 + u2 * r21, u0 * r02 + u1 * r12 + u2 * r22
        w0, w1, w2 = v0 * r00 + v1 * r10 + v2 * r20, v0 * r01 + v1 * r11 + v2 * r21, v0 * r02 + v1 * r12 + v2 * r22
        p00, p01, p02 = t0 * s0, t1 * s1, t2 * s2
        p10, p11, p12 = w0 * s0, w1 * s1, w2 * s2
        ca = p00 * p00 + p01 * p01 + p02 * p02 + LOW_PASS
        cb = p00 * p10 + p01 * p11 + p02 * p12
        cc = p10 * p10 + p11 * p11 + p12 * p12 + LOW_PASS
        det = ca * cc - cb * cb
        d2 = det * det
        # conics = (c, -b, a) / det.
        g0, g1, g2 = g_conics[i, 0], g_conics[i, 1], g_conics[i, 2]
        ga = (-g0 * cc * cc + g1 * cb * cc - g2 * cb * cb) / d2
        gb = (2.0 * g0 * cb * cc - g1 * (det + 2.0 * cb * cb) + 2.0 * g2 * ca * cb) / d2
        gc = (-g0 * cb * cb + g1 * ca * cb - g2 * ca * ca) / d2
        e00, e01, e02 = 2.0 * ga * p00 + gb * p10, 2.0 * ga * p01 + gb * p11, 2.0 * ga * p02 + gb * p12  # d/dp0
        e10, e11, e12 = 2.0 * gc * p10 + gb * p00, 2.0 * gc * p11 + gb * p01, 2.0 * gc * p12 + gb * p02  # d/dp1
        out_scales[i, 0] = (t0 * e00 + w0 * e10) * s0
        out_scales[i, 1] = (t1 * e01 + w1 * e11) * s1
        out_scales[i, 2] = (t2 * e02 + w2 * e12) * s2
        # Into R_g: d/dR_jk = (u_j e0_k + v_j e1_k) s_k.
        f0, f1, f2 = e00 * s0, e01 * s1, e02 * s2
        h0, h1, h2 = e10 * s0, e11 * s1, e12 * s2
        g00, g01, g02 = u0 * f0 + v0 * h0, u0 * f1 + v0 * h1, u0 * f2 + v0 * h2
        g10, g11, g12 = u1 * f0 + v1 * h0, u1 * f1 + v1 * h1, u1 * f2 + v1 * h2
        g20, g21, g22 = u2 * f0 + v2 * h0, u2 * f1 + v2 * h1, u2 * f2 + v2 * h2
        gw = 2.0 * (-c * g01 + b * g02 + c * g10 - a * g12 - b * g20 + a * g21)
        gqa = 2.0 * (b * g01 + c * g02 + b * g10 - 2.0 * a * g11 - w * g12 + c * g20 + w * g21 - 2.0 * a * g22)
        gqb = 2.0 * (-2.0 * b * g00 + a * g01 + w * g02 + a * g10 + c * g12 - w * g20 + c * g21 - 2.0 * b * g22)
        gqc = 2.0 * (-2.0 * c * g00 - w * g01 + a * g02 + w * g10 - 2.0 * c * g11 + b * g12 + a * g20 + b * g21)
        along = (w * gw + a * gqa + b * gqb + c * gqc) if qn > 1e-12 else 0.0  # normalisation's projection
        out_quats[i, 0] = (gw - w * along) / qd
        out_quats[i, 1] = (gqa - a * along) / qd
        out_quats[i, 2] = (gqb - b * along) / qd
        out_quats[i, 3] = (gqc - c * along) / qd
        # Into the Jacobian: d/djw_j = sum_k R_jk s_k e_k.
        k0 = r00 * f0 + r01 * f1 + r02 * f2
        k1 = r10 * f0 + r11 * f1 + r12 * f2
        k2 = r20 * f0 + r21 * f1 + r22 * f2
        l0 = r00 * h0 + r01 * h1 + r02 * h2
        l1 = r10 * h0 + r11 * h1 + r12 * h2
        l2 = r20 * h0 + r21 * h1 + r22 * h2
        gj00 = k0 * rot[0, 0] + k1 * rot[0, 1] + k2 * rot[0, 2]
        gj02 = k0 * rot[2, 0] + k1 * rot[2, 1] + k2 * rot[2, 2]
        gj11 = l0 * rot[1, 0] + l1 * rot[1, 1] + l2 * rot[1, 2]
        gj12 = l0 * rot[2, 0] + l1 * rot[2, 1] + l2 * rot[2, 2]
        inside_x = 1.0 if -lim_x <= tx <= lim_x else 0.0
        inside_y = 1.0 if -lim_y <= ty <= lim_y else 0.0
        gx -= gj02 * fx / zz * inside_x
        gy -= gj12 * fy / zz * inside_y
        gz += (-gj00 * fx - gj11 * fy + gj02 * fx * (ctx + tx * inside_x) + gj12 * fy * (cty + ty * inside_y)) / zz
        if not in_front:
            gz = 0.0
        out_means[i, 0] = gmx + rot[0, 0] * gx + rot[1, 0] * gy + rot[2, 0] * gz
        out_means[i, 1] = gmy + rot[0, 1] * gx + rot[1, 1] * gy + rot[2, 1] * gz
        out_means[i, 2] = gmz + rot[0, 2] * gx + rot[1, 2] * gy + rot[2, 2] * gz


def project_backward_fast(arrays, degree, camera, grads):  # noqa: ANN001, ANN201 - arrays, a Camera
    """Gradients (float32 arrays) of ``_project_kernel.project_fast``'s inputs ``arrays`` from its outputs' ``grads``
    (float64: means2d, conics, depths, colors, opacity)."""
    means, quats, scales, opacities, dc, rest = arrays
    g_means2d, g_conics, g_depths, g_colors, g_opacity = grads
    outs = tuple(np.empty_like(a) for a in arrays)
    rot, trans, center = (np.ascontiguousarray(t.detach().cpu().numpy(), dtype=np.float64)
                          for t in (camera.R, camera.t, camera.center))  # fmt: skip
    project_backward(means, quats, scales, opacities, dc, rest, (degree + 1) ** 2, rot, trans, center,
                     float(np.float32(camera.fx)), float(np.float32(camera.fy)), camera.width, camera.height,
                     float(camera.near), _C2, _C3, g_means2d, g_conics, g_depths, g_colors, g_opacity,
                     *outs)  # fmt: skip
    return outs
