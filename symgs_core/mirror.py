"""Mirror planes and the exact reflection of a Gaussian set across one.

A plane is a unit normal n and an offset g: the points x with n.x = g. H = I - 2 n n^T.
  mean:     x' = x - 2 (n.x - g) n
  rotation: H R = -R_pi(n) R with R_pi(n) = 2 n n^T - I, so the reflected covariance H R S^2 R^T H equals
            R' S^2 R'^T for the proper rotation R' = R_pi(n) R; as quaternions q' = (0, n) (x) q.
  SH:       c'(d) = c(H d), band by band (see ``sh.reflect_sh_rest``).
Scales and opacities are unchanged.

Levels of mirrors (``expand``): the archive keeps a stored set S (an ordered list of Gaussians), the mirror planes
M_0..M_L (M_0 the dominant one) and a bit matrix B [|S|, L+1]: B[i, l] says that Gaussian i is *left* at level l
(kept and reflected across M_l). Decoding runs from level L down to 0: at level l the members of the current set
whose bit l is set are reflected across M_l and appended, in order, and each reflection inherits the bits of its
source. So a reflection made at a local level is mirrored again by every larger mirror its source belongs to. The
expansion is exact, O(N) per level, and needs no nearest-neighbour search.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from .scene import GaussianScene
from .sh import reflect_sh_rest


def canonical_sign(normal: Sequence[float]) -> float:
    """1 or -1: the sign that turns a plane's normal [3] (and its offset) into the hemisphere whose largest-magnitude
    component is positive (the first of equal ones), the one way of writing a plane that detection and archives
    use."""
    axis = max(range(3), key=lambda i: abs(normal[i]))
    return 1.0 if normal[axis] >= 0 else -1.0


@dataclass(frozen=True)
class Plane:
    """A mirror plane n.x = offset; ``normal`` is a unit 3-vector (a tuple so planes are hashable and JSON-able)."""

    normal: tuple[float, float, float]
    offset: float

    def __post_init__(self) -> None:
        norm = math.hypot(*self.normal)
        if not abs(norm - 1.0) < 1e-4:
            raise ValueError(f"plane normal must be unit length, got norm {norm}")

    @staticmethod
    def from_tensor(normal: Tensor, offset: Tensor | float) -> Plane:
        n = normal.detach().to(torch.float64).flatten()
        norm = n.norm()
        if not torch.isfinite(norm) or norm == 0:
            raise ValueError(f"plane normal must be finite and non-zero, got {normal.tolist()}")
        g = float(offset) / float(norm)
        n = n / norm
        return Plane((float(n[0]), float(n[1]), float(n[2])), g)

    def canonical(self) -> Plane:
        """The same plane with its normal in the hemisphere whose largest-magnitude component is positive."""
        if canonical_sign(self.normal) > 0:
            return self
        n = self.normal
        return Plane((-n[0], -n[1], -n[2]), -self.offset)

    def tensor(self, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> tuple[Tensor, Tensor]:
        return (
            torch.tensor(self.normal, device=device, dtype=dtype),
            torch.tensor(self.offset, device=device, dtype=dtype),
        )

    def signed_distance(self, points: Tensor) -> Tensor:
        n, g = self.tensor(points.device, points.dtype)
        return points @ n - g

    def angle_deg(self, other: Plane) -> float:
        """Angle between the two planes in degrees, 0..90 (a normal and its negation are one plane)."""
        cos = abs(sum(x * y for x, y in zip(self.normal, other.normal, strict=True)))
        return math.degrees(math.acos(min(1.0, cos)))

    def gap_at(self, other: Plane, point: Tensor) -> float:
        """How far apart the two planes lie at ``point`` [3]: the difference of its signed distances to them, with
        the normals turned the same way."""
        p = point.detach().to(torch.float64)
        mine = float(self.signed_distance(p))
        theirs = float(other.signed_distance(p))
        aligned = sum(x * y for x, y in zip(self.normal, other.normal, strict=True)) >= 0
        return abs(mine - (theirs if aligned else -theirs))


def householder(normal: Tensor) -> Tensor:
    """H = I - 2 n n^T [3, 3] for a unit normal [3]."""
    return torch.eye(3, dtype=normal.dtype, device=normal.device) - 2.0 * torch.outer(normal, normal)


def reflect_points(points: Tensor, normal: Tensor, offset: Tensor | float) -> Tensor:
    """Mirror images [N, 3] of ``points`` [N, 3] across the plane n.x = offset (n unit)."""
    d = points @ normal - offset
    return points - 2.0 * d[:, None] * normal


def reflect_quats(quats: Tensor, normal: Tensor) -> Tensor:
    """Quaternions [N, 4] (w, x, y, z) of the reflected Gaussians: (0, n) (x) q = (-n.v, w n + n x v)."""
    w, v = quats[:, :1], quats[:, 1:]
    n = normal.expand_as(v)
    return torch.cat([-(v @ normal)[:, None], w * n + torch.linalg.cross(n, v, dim=-1)], dim=-1)


def _unit(normal: Tensor, offset: Tensor | float) -> tuple[Tensor, Tensor | float]:
    """Normalise a plane given by any non-zero normal; differentiable so optimisers may move it freely."""
    norm = normal.norm()
    return normal / norm, offset / norm


def reflect(scene: GaussianScene, normal: Tensor, offset: Tensor | float) -> GaussianScene:
    """The scene mirrored across the plane normal.x = offset; differentiable in the scene and the plane.

    ``normal`` [3] need not be unit: the plane is normalised first (the offset with it).
    """
    if normal.shape != (3,):
        raise ValueError(f"normal must have shape (3,), got {tuple(normal.shape)}")
    normal = normal.to(scene.means.dtype)
    n, g = _unit(normal, offset)
    return GaussianScene(
        means=reflect_points(scene.means, n, g),
        quats=reflect_quats(scene.quats, n),
        scales=scene.scales,
        opacities=scene.opacities,
        sh_dc=scene.sh_dc,
        sh_rest=reflect_sh_rest(scene.sh_rest, householder(n)),
    )


Plan = list[tuple[int, Tensor]]  # (level, indices [M] of the current set it reflects), from the last level to 0


def expansion_plan(bits: Tensor) -> Plan:
    """Which Gaussians each level reflects when a stored set with ``bits`` [|S|, L+1] is expanded: it depends on the
    bits alone, so a fine-tune that keeps them computes it once (finding the members waits for the device)."""
    plan: Plan = []
    cur_bits = bits.to(torch.bool)
    for level in range(bits.shape[1] - 1, -1, -1):
        index = torch.nonzero(cur_bits[:, level])[:, 0]
        if index.numel():
            plan.append((level, index))
            cur_bits = torch.cat([cur_bits, cur_bits[index]])
    return plan


def expand(
    stored: GaussianScene, normals: Tensor, offsets: Tensor, bits: Tensor, plan: Plan | None = None
) -> tuple[GaussianScene, Tensor]:
    """Expand ``stored`` through the levels.

    normals [L+1, 3], offsets [L+1] (level 0 first), bits [|S|, L+1] bool; ``plan``: ``expansion_plan(bits)``, when
    the caller keeps it. Returns the expanded scene and, for each of its Gaussians, the index [N_out] of the stored
    Gaussian it derives from. Differentiable in the stored attributes and in the planes.
    """
    levels = normals.shape[0]
    if tuple(offsets.shape) != (levels,) or tuple(bits.shape) != (len(stored), levels):
        raise ValueError(
            f"expand: normals {tuple(normals.shape)}, offsets {tuple(offsets.shape)} and bits "
            f"{tuple(bits.shape)} disagree with {len(stored)} stored Gaussians"
        )
    scene = stored
    origin = torch.arange(len(stored), device=stored.device)
    for level, index in expansion_plan(bits) if plan is None else plan:
        scene = GaussianScene.cat([scene, reflect(scene.select(index), normals[level], offsets[level])])
        origin = torch.cat([origin, origin[index]])
    return scene, origin


def expand_planes(stored: GaussianScene, planes: list[Plane], bits: Tensor) -> GaussianScene:
    """``expand`` with planes given as ``Plane`` objects (level 0 first)."""
    if planes:
        normals = torch.tensor([p.normal for p in planes], dtype=stored.means.dtype, device=stored.device)
        offsets = torch.tensor([p.offset for p in planes], dtype=stored.means.dtype, device=stored.device)
    else:
        normals = torch.zeros(0, 3, dtype=stored.means.dtype, device=stored.device)
        offsets = torch.zeros(0, dtype=stored.means.dtype, device=stored.device)
    return expand(stored, normals, offsets, bits)[0]
