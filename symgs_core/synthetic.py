"""Synthetic Gaussian scenes with planted mirrors, for tests, benchmarks and demos.

Objects are built from parts (boxes, ellipsoids, cylinders) whose surfaces are covered by flat Gaussians lying in the
tangent plane, sized so that neighbours overlap, so the scenes look like objects when rendered. A symmetric object is
built in a frame where its mirror is the plane x = 0: parts straddling the plane are centred on it and rotated only
about the x axis; every other part sits wholly at x > 0. The x > 0 half is sampled, and the other half is either its
exact reflection (``capture="twins"``) or an independent sample of the mirrored surface (``capture="independent"``:
the halves do not pair up one to one and their attributes differ, as in real captures).

Everything is deterministic given ``seed`` and vectorised, so the same code makes a few thousand Gaussians for tests
and millions for benchmarks.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import torch
from torch import Tensor

from .mirror import Plane, reflect
from .scene import SH_REST_COUNT, GaussianScene, sh_degree_for_rest
from .sh import C0, sh_transform_matrix

SceneKind = Literal["global", "local", "nested", "asymmetric"]
Capture = Literal["twins", "independent"]
Shape = Literal["box", "ellipsoid", "cylinder", "blob"]

_X = torch.tensor([1.0, 0.0, 0.0])
# Clutter fills the object's box and a tenth of its size around it.
CLUTTER_PAD = 0.1
# Surroundings: a slab the object stands on, as a table or a floor it was captured on, SURROUNDINGS_SPAN times the
# object's width and depth, half its height thick, its top SURROUNDINGS_CONTACT of that height into the object's base,
# its middle SURROUNDINGS_OFFSET of its width and depth away from the object's: the slab's own symmetries are not the
# object's.
SURROUNDINGS_SPAN = 4.0
SURROUNDINGS_CONTACT = 0.05
SURROUNDINGS_OFFSET = (0.3, 0.2)


@dataclass(frozen=True)
class Pose:
    """A similarity transform x -> scale * R x + translation, R given as a unit quaternion (w, x, y, z)."""

    quat: tuple[float, float, float, float] = (1.0, 0.0, 0.0, 0.0)
    translation: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: float = 1.0

    def __post_init__(self) -> None:
        if not self.scale > 0:
            raise ValueError(f"pose scale must be positive, got {self.scale}")
        norm = math.sqrt(sum(q * q for q in self.quat))
        if abs(norm - 1.0) > 1e-4:
            raise ValueError(f"pose quaternion must be unit length, got norm {norm}")

    @staticmethod
    def random(seed: int, scale_range: tuple[float, float] = (0.1, 10.0), max_shift: float = 10.0) -> Pose:
        """A random rotation, a translation up to ``max_shift`` per axis and a log-uniform scale."""
        gen = torch.Generator().manual_seed(seed)
        q = torch.nn.functional.normalize(torch.randn(4, generator=gen, dtype=torch.float64), dim=0)
        t = (torch.rand(3, generator=gen, dtype=torch.float64) * 2 - 1) * max_shift
        lo, hi = math.log(scale_range[0]), math.log(scale_range[1])
        s = math.exp(lo + (hi - lo) * float(torch.rand(1, generator=gen, dtype=torch.float64)))
        return Pose(tuple(q.tolist()), tuple(t.tolist()), s)

    def matrix(self) -> Tensor:
        """Rotation [3, 3] (float64)."""
        return quat_to_matrix(torch.tensor(self.quat, dtype=torch.float64))

    def apply_plane(self, plane: Plane) -> Plane:
        n = self.matrix() @ torch.tensor(plane.normal, dtype=torch.float64)
        t = torch.tensor(self.translation, dtype=torch.float64)
        return Plane.from_tensor(n, self.scale * plane.offset + float(n @ t))


@dataclass
class SyntheticScene:
    """A synthetic scene and its ground truth.

    planes  the planted mirrors, most dominant (most Gaussians) first
    left    per plane, indices [L_k] of the planted kept half
    right   per plane, indices [R_k] of the planted mirrored half (the exact reflection of ``left`` for twins)
    clutter indices [C] of the asymmetric extra Gaussians
    """

    scene: GaussianScene
    planes: list[Plane]
    left: list[Tensor]
    right: list[Tensor]
    clutter: Tensor


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a (x) b of quaternions [..., 4] (w, x, y, z)."""
    aw, av = a[..., :1], a[..., 1:]
    bw, bv = b[..., :1], b[..., 1:]
    w = aw * bw - (av * bv).sum(-1, keepdim=True)
    v = aw * bv + bw * av + torch.linalg.cross(av.expand_as(bv), bv.expand_as(av), dim=-1)
    return torch.cat([w, v], dim=-1)


def quat_to_matrix(q: Tensor) -> Tensor:
    """Rotation matrices [..., 3, 3] of unit quaternions [..., 4] (w, x, y, z)."""
    w, x, y, z = q.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ]  # fmt: skip
    return torch.stack(rows, dim=-1).reshape(*q.shape[:-1], 3, 3)


def apply_pose(scene: GaussianScene, pose: Pose) -> GaussianScene:
    """The scene moved by ``pose``: means, rotations, log-scales and view-dependent colour all follow."""
    dtype, device = scene.means.dtype, scene.device
    rot = pose.matrix()
    q = torch.tensor(pose.quat, dtype=dtype, device=device)
    t = torch.tensor(pose.translation, dtype=dtype, device=device)
    sh_rest = scene.sh_rest
    if sh_rest.shape[1]:
        # Rotated colour: c'(d) = c(R^T d).
        tm = sh_transform_matrix(rot.T, scene.sh_degree)[1:, 1:].to(dtype=dtype, device=device)
        sh_rest = torch.einsum("kj,njc->nkc", tm, sh_rest)
    return GaussianScene(
        means=pose.scale * scene.means @ rot.to(dtype=dtype, device=device).T + t,
        quats=quat_mul(q.expand_as(scene.quats), scene.quats),
        scales=scene.scales + math.log(pose.scale),
        opacities=scene.opacities,
        sh_dc=scene.sh_dc,
        sh_rest=sh_rest,
    )


# ---------------------------------------------------------------------------------------------------------------
# Parts and their surfaces


@dataclass
class _Part:
    shape: Shape
    half: Tensor  # [3] half extents (semi-axes; cylinder: two radii and the half height)
    centre: Tensor  # [3]
    quat: Tensor  # [4]
    colour: Tensor  # [3] base RGB
    colour_noise: float  # per-Gaussian RGB jitter (0: a flat colour, one big cluster)
    stripes: float  # stripe frequency along the part's own z axis, 0 for none
    sh: Tensor  # [K, 3] the part's view-dependent colour
    warp: Tensor  # [W, 6] blob deformation, one wave per row: amplitude, frequency, phase, direction (blobs only)

    def area(self) -> float:
        a, b, c = (float(v) for v in self.half)
        if self.shape == "box":
            return 8.0 * (a * b + a * c + b * c)
        if self.shape == "cylinder":
            perimeter = 2.0 * math.pi * math.sqrt((a * a + b * b) / 2.0)
            return perimeter * 2.0 * c + 2.0 * math.pi * a * b
        p = 1.6075  # Knud Thomsen's ellipsoid surface approximation
        return 4.0 * math.pi * (((a * b) ** p + (a * c) ** p + (b * c) ** p) / 3.0) ** (1.0 / p)

    def radius(self) -> float:
        return float(self.half.norm()) * (1.3 if self.shape == "blob" else 1.0)


def _surface(part: _Part, m: int, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Points [m, 3] on the part's surface in its own frame, and outward unit normals [m, 3]."""
    h = part.half
    if part.shape == "box":
        a, b, c = h.tolist()
        face_area = torch.tensor([b * c, b * c, a * c, a * c, a * b, a * b])
        face = torch.multinomial(face_area, m, replacement=True, generator=gen)
        axis, sign = face // 2, 1.0 - 2.0 * (face % 2).float()
        p = (torch.rand(m, 3, generator=gen) * 2 - 1) * h
        rows = torch.arange(m)
        p[rows, axis] = sign * h[axis]
        normal = torch.zeros(m, 3)
        normal[rows, axis] = sign
        return p, normal
    if part.shape == "cylinder":
        a, b, c = h.tolist()
        side = 2.0 * math.pi * math.sqrt((a * a + b * b) / 2.0) * 2.0 * c
        on_side = torch.rand(m, generator=gen) * (side + 2.0 * math.pi * a * b) < side
        theta = torch.rand(m, generator=gen) * 2.0 * math.pi
        radial = torch.where(on_side, torch.ones(m), torch.sqrt(torch.rand(m, generator=gen)))
        cap = torch.where(torch.rand(m, generator=gen) < 0.5, -1.0, 1.0)
        z = torch.where(on_side, (torch.rand(m, generator=gen) * 2 - 1) * c, cap * c)
        p = torch.stack([a * radial * torch.cos(theta), b * radial * torch.sin(theta), z], dim=-1)
        side_n = torch.stack([torch.cos(theta) / a, torch.sin(theta) / b, torch.zeros(m)], dim=-1)
        cap_n = torch.stack([torch.zeros(m), torch.zeros(m), cap], dim=-1)
        normal = torch.where(on_side[:, None], side_n, cap_n)
        return p, torch.nn.functional.normalize(normal, dim=-1)
    u = torch.nn.functional.normalize(torch.randn(m, 3, generator=gen), dim=-1)
    if part.shape == "blob":
        # A lumpy ellipsoid: the radius is modulated by four waves in random directions, so the shape has no mirror.
        amp, freq, phase, direction = part.warp[:, 0], part.warp[:, 1], part.warp[:, 2], part.warp[:, 3:]
        u = u * (1.0 + (amp * torch.sin(freq * (u @ direction.T) + phase)).sum(-1, keepdim=True))
    return u * h, torch.nn.functional.normalize(u / h, dim=-1)


def _align_z(normal: Tensor, twist: Tensor) -> Tensor:
    """Quaternions [m, 4] of rotations taking e_z to ``normal`` [m, 3], after a twist [m] (radians) about e_z."""
    q = torch.stack([1.0 + normal[:, 2], -normal[:, 1], normal[:, 0], torch.zeros_like(twist)], dim=-1)
    flipped = normal[:, 2] < -1.0 + 1e-6  # e_z -> -e_z: the formula degenerates, use a half turn about x
    q[flipped] = torch.tensor([0.0, 1.0, 0.0, 0.0])
    q = torch.nn.functional.normalize(q, dim=-1)
    zero = torch.zeros_like(twist)
    spin = torch.stack([torch.cos(twist / 2), zero, zero, torch.sin(twist / 2)], dim=-1)
    return quat_mul(q, spin)


def _logit(p: Tensor) -> Tensor:
    return torch.log(p) - torch.log1p(-p)


def _sample_part(part: _Part, m: int, gen: torch.Generator) -> GaussianScene:
    """``m`` Gaussians covering the part's surface."""
    local, local_n = _surface(part, m, gen)
    rot = quat_to_matrix(part.quat)
    means = local @ rot.T + part.centre
    normal = local_n @ rot.T
    spacing = math.sqrt(part.area() / max(m, 1))
    tangent = spacing * (0.45 + 0.35 * torch.rand(m, 2, generator=gen))
    thickness = spacing * (0.05 + 0.10 * torch.rand(m, 1, generator=gen))
    quats = _align_z(normal, torch.rand(m, generator=gen) * 2.0 * math.pi)
    rgb = part.colour + part.colour_noise * torch.randn(m, 3, generator=gen)
    if part.stripes > 0:
        rgb = rgb * torch.where(torch.sin(part.stripes * local[:, 2:3]) > 0, 1.0, 0.6)
    opacity = torch.where(
        torch.rand(m, generator=gen) < 0.9,
        0.5 + 0.49 * torch.rand(m, generator=gen),
        0.1 + 0.4 * torch.rand(m, generator=gen),
    )
    k = part.sh.shape[0]
    sh_rest = part.sh + 0.02 * torch.randn(m, k, 3, generator=gen)
    return GaussianScene(
        means=means,
        quats=quats,
        scales=torch.log(torch.cat([tangent, thickness], dim=-1)),
        opacities=_logit(opacity),
        sh_dc=(rgb.clamp(0.02, 0.98) - 0.5) / C0,
        sh_rest=sh_rest,
    )


def _random_quat(gen: torch.Generator) -> Tensor:
    return torch.nn.functional.normalize(torch.randn(4, generator=gen), dim=0)


def _x_turn(angle: float) -> Tensor:
    """A rotation about the x axis: it maps the plane x = 0 to itself, so a centred part stays symmetric."""
    return torch.tensor([math.cos(angle / 2), math.sin(angle / 2), 0.0, 0.0])


def _u(gen: torch.Generator, lo: float, hi: float) -> float:
    return lo + (hi - lo) * float(torch.rand(1, generator=gen))


def _uv(gen: torch.Generator, lo: float, hi: float, m: int) -> Tensor:
    return lo + (hi - lo) * torch.rand(m, generator=gen)


def _random_colour(gen: torch.Generator) -> Tensor:
    """A saturated RGB colour from a random hue."""
    h = float(torch.rand(1, generator=gen))
    s = _u(gen, 0.45, 0.9)
    v = _u(gen, 0.45, 0.95)
    k = (torch.tensor([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    return v - v * s * torch.clamp(torch.minimum(k, 4.0 - k), 0.0, 1.0)


def _new_part(gen: torch.Generator, shape: Shape, half: Tensor, centre: Tensor, quat: Tensor, k: int) -> _Part:
    flat = float(torch.rand(1, generator=gen)) < 0.3
    # Rest coefficient i belongs to band l = isqrt(i + 1); higher bands get smaller amplitudes.
    band = torch.tensor([0.12 / math.isqrt(i + 1) for i in range(k)])
    return _Part(
        shape=shape,
        half=half,
        centre=centre,
        quat=quat,
        colour=_random_colour(gen),
        colour_noise=0.0 if flat else _u(gen, 0.02, 0.08),
        stripes=0.0 if float(torch.rand(1, generator=gen)) < 0.6 else _u(gen, 10.0, 30.0),
        sh=band[:, None] * torch.randn(k, 3, generator=gen),
        warp=torch.cat(
            [
                torch.stack([_uv(gen, 0.2, 0.35, 4), _uv(gen, 3.0, 7.0, 4), _uv(gen, 0.0, 2 * math.pi, 4)], dim=1),
                torch.nn.functional.normalize(torch.randn(4, 3, generator=gen), dim=1),
            ],
            dim=1,
        ),
    )


_SHAPES: tuple[Shape, ...] = ("box", "ellipsoid", "cylinder")


def _random_shape(gen: torch.Generator) -> Shape:
    return _SHAPES[int(torch.randint(len(_SHAPES), (1,), generator=gen))]


def _symmetric_parts(gen: torch.Generator, parts: int, k: int) -> tuple[list[_Part], list[_Part]]:
    """An object with the mirror x = 0: (parts centred on the plane, parts wholly at x > 0)."""
    body_half = torch.tensor([_u(gen, 0.25, 0.4), _u(gen, 0.2, 0.35), _u(gen, 0.4, 0.6)])
    body = _new_part(gen, "box", body_half, torch.zeros(3), _x_turn(_u(gen, -0.3, 0.3)), k)
    head_half = _uv(gen, 0.12, 0.22, 3)
    head_centre = torch.tensor([0.0, _u(gen, 0.05, 0.2), float(body_half[2]) + float(head_half[2]) * 0.8])
    head = _new_part(gen, "ellipsoid", head_half, head_centre, _x_turn(_u(gen, -0.5, 0.5)), k)
    side = []
    for _ in range(max(parts - 2, 0)):
        half = _uv(gen, 0.05, 0.28, 3)
        reach = float(half.norm())
        centre = torch.tensor([reach + _u(gen, 0.02, 0.45), _u(gen, -0.7, 0.7), _u(gen, -0.8, 0.8)])
        side.append(_new_part(gen, _random_shape(gen), half, centre, _random_quat(gen), k))
    return [body, head], side


def _asymmetric_parts(gen: torch.Generator, parts: int, k: int) -> list[_Part]:
    out = []
    for _ in range(max(parts, 1)):
        half = _uv(gen, 0.1, 0.35, 3)
        out.append(_new_part(gen, "blob", half, _uv(gen, -0.7, 0.7, 3), _random_quat(gen), k))
    return out


def _sample_parts(parts: list[_Part], counts: list[int], gen: torch.Generator, k: int) -> GaussianScene:
    scenes = [_sample_part(p, c, gen) for p, c in zip(parts, counts, strict=True) if c > 0]
    return GaussianScene.cat(scenes) if scenes else GaussianScene.empty(sh_degree_for_rest(k))


def _allocate(parts: list[_Part], total: int, weights: list[float] | None = None) -> list[int]:
    """Gaussians per part, proportional to surface area (times ``weights``), at least 4 each."""
    w = torch.tensor([p.area() * (weights[i] if weights else 1.0) for i, p in enumerate(parts)])
    return [max(4, int(round(float(x)))) for x in w / w.sum() * total]


@dataclass
class _Object:
    scene: GaussianScene
    left: Tensor  # [L] planted kept half (indices into scene)
    right: Tensor  # [R] planted mirrored half
    sub: tuple[Plane, Tensor, Tensor] | None = None  # a local mirror inside the left half (nested scenes)


@dataclass
class _Design:
    """A symmetric object with its mirror at x = 0: its parts and how many Gaussians each gets."""

    parts: list[_Part]
    counts: list[int]
    k: int

    @staticmethod
    def random(gen: torch.Generator, n: int, parts: int, k: int) -> _Design:
        centred, side = _symmetric_parts(gen, parts, k)
        # Centred parts are sampled whole and cut at the plane, so they get twice their half's share.
        counts = _allocate(centred + side, n // 2, [0.5] * len(centred) + [1.0] * len(side))
        counts = [2 * c for c in counts[: len(centred)]] + counts[len(centred) :]
        return _Design(centred + side, counts, k)

    def half(self, gen: torch.Generator) -> GaussianScene:
        """One sample of the x > 0 half."""
        s = _sample_parts(self.parts, self.counts, gen, self.k)
        return s.select(s.means[:, 0] > 0)

    def whole(self, gen: torch.Generator, capture: Capture) -> _Object:
        half = self.half(gen)
        other = reflect(half if capture == "twins" else self.half(gen), _X, 0.0)
        idx = torch.arange(len(half) + len(other))
        return _Object(GaussianScene.cat([half, other]), idx[: len(half)], idx[len(half) :])


def _nested_object(gen: torch.Generator, samples: torch.Generator, n: int, parts: int, k: int,
                   capture: Capture) -> _Object:  # fmt: skip
    """A symmetric object (mirror x = 0) whose x > 0 half holds a smaller symmetric object with its own mirror;
    the design drawn from ``gen``, the Gaussians from ``samples``."""
    sub_share = 0.4
    main = _Design.random(gen, int(n * (1 - sub_share)), parts, k)
    sub = _Design.random(gen, int(n * sub_share / 2), max(parts // 2, 3), k)
    sub_pose = Pose(tuple(_random_quat(gen).tolist()), (0.95, _u(gen, -0.3, 0.3), _u(gen, -0.3, 0.3)), 0.3)
    sub_obj = sub.whole(samples, capture)
    half = GaussianScene.cat([main.half(samples), apply_pose(sub_obj.scene, sub_pose)])
    if capture == "twins":
        other = reflect(half, _X, 0.0)
    else:
        again = GaussianScene.cat([main.half(samples), apply_pose(sub.whole(samples, capture).scene, sub_pose)])
        other = reflect(again, _X, 0.0)
    idx = torch.arange(len(half) + len(other))
    base = len(half) - len(sub_obj.scene)
    sub_plane = sub_pose.apply_plane(Plane((1.0, 0.0, 0.0), 0.0))
    return _Object(
        GaussianScene.cat([half, other]),
        idx[: len(half)],
        idx[len(half) :],
        (sub_plane, sub_obj.left + base, sub_obj.right + base),
    )


def _clutter(gen: torch.Generator, count: int, means: Tensor, scales: Tensor, k: int, pad: float) -> GaussianScene:
    """Asymmetric extra Gaussians: uniform in the bounding box grown by ``pad`` of its size on every side, random
    colours, sizes, rotations and opacities."""
    lo, hi = means.min(0).values, means.max(0).values
    margin = pad * (hi - lo)
    lo, hi = lo - margin, hi + margin
    s_lo, s_hi = torch.quantile(scales.flatten()[:100_000], torch.tensor([0.05, 0.95])).tolist()
    return GaussianScene(
        means=lo + (hi - lo) * torch.rand(count, 3, generator=gen),
        quats=torch.nn.functional.normalize(torch.randn(count, 4, generator=gen), dim=-1),
        scales=s_lo + (s_hi - s_lo) * torch.rand(count, 3, generator=gen),
        opacities=_logit(0.3 + 0.65 * torch.rand(count, generator=gen)),
        sh_dc=(torch.rand(count, 3, generator=gen) * 0.96 + 0.02 - 0.5) / C0,
        sh_rest=0.05 * torch.randn(count, k, 3, generator=gen),
    )


def surroundings_of(means: Tensor, scales: Tensor, count: int, gen: torch.Generator, k: int) -> GaussianScene:
    """``count`` asymmetric Gaussians (``k`` higher SH coefficients) in a slab under the object of ``means`` [N, 3]
    (and log-scales [N, 3]), in contact with it: what an object captured on a table stands among."""
    lo, hi = means.min(0).values, means.max(0).values
    size = hi - lo
    middle = (lo + hi) / 2
    half = torch.stack([SURROUNDINGS_SPAN * size[0], SURROUNDINGS_SPAN * size[1], 0.5 * size[2]]) / 2
    top = lo[2] + SURROUNDINGS_CONTACT * size[2]
    dx, dy = (2 * share * h for share, h in zip(SURROUNDINGS_OFFSET, half[:2], strict=True))
    slab = torch.stack([middle[0] + dx, middle[1] + dy, top - half[2]])
    # ``_clutter`` fills a box around points: the slab's two far corners.
    corners = torch.stack([slab - half, slab + half])
    return _clutter(gen, count, corners, scales, k, 0.0)


def synthetic_scene(
    kind: SceneKind = "global",
    *,
    n: int = 4000,
    seed: int = 0,
    sh_degree: int = 0,
    parts: int = 8,
    objects: int = 2,
    capture: Capture = "twins",
    noise: float = 0.0,
    clutter: float = 0.0,
    surroundings: float = 0.0,
    pose: Pose | None = None,
    sample_seed: int | None = None,
) -> SyntheticScene:
    """A scene of about ``n`` object Gaussians (plus clutter) with planted mirrors.

    kind      "global": one symmetric object; "local": ``objects`` symmetric objects of decreasing sizes, apart,
              mirrors of different orientations; "nested": a symmetric object whose kept half holds a smaller
              symmetric object (the second plane, inside ``left[0]``); "asymmetric": lumpy parts with no mirror at all
    parts     parts per object (two of them straddle the mirror)
    objects   symmetric objects of a "local" scene, 1..7
    capture   "twins": the halves are exact reflections; "independent": each half sampled on its own
    noise     std of positional noise on the object Gaussians, as a fraction of the object's size (about 1)
    clutter   asymmetric extra Gaussians, as a fraction of the object Gaussians, in the object's box
    surroundings  asymmetric Gaussians the object stands among, as a multiple of the object Gaussians, in a slab
              under it (``surroundings_of``; both kinds are ``clutter`` in the result)
    pose      a similarity transform applied to the whole scene (planes follow)
    sample_seed  draws the Gaussians from a generator of their own (None: ``seed``'s, after the design): the same
              ``seed`` then gives the same objects whatever ``n``, ``capture`` and ``sample_seed``, sampled anew, e.g.
              a dense exact-twin sample to photograph as the truth and a capture of it (``bench_pipeline --photos``)
    """
    if sh_degree not in SH_REST_COUNT:
        raise ValueError(f"sh_degree must be 0..3, got {sh_degree}")
    if n < 16:
        raise ValueError(f"a synthetic scene needs n >= 16 Gaussians, got {n}")
    if not 1 <= objects <= 7:
        raise ValueError(f"objects must be 1..7, got {objects}")
    if noise < 0 or clutter < 0 or surroundings < 0:
        raise ValueError(f"noise, clutter and surroundings must be non-negative, got noise={noise}, clutter={clutter}, "
                         f"surroundings={surroundings}")  # fmt: skip
    k = SH_REST_COUNT[sh_degree]
    gen = torch.Generator().manual_seed(seed)
    samples = gen if sample_seed is None else torch.Generator().manual_seed(sample_seed)
    x_plane = Plane((1.0, 0.0, 0.0), 0.0)

    planes: list[Plane] = []
    lefts: list[Tensor] = []
    rights: list[Tensor] = []
    if kind == "global":
        obj = _Design.random(gen, n, parts, k).whole(samples, capture)
        scene, planes, lefts, rights = obj.scene, [x_plane], [obj.left], [obj.right]
    elif kind == "nested":
        obj = _nested_object(gen, samples, n, parts, k, capture)
        assert obj.sub is not None
        scene = obj.scene
        planes, lefts, rights = [x_plane, obj.sub[0]], [obj.left, obj.sub[1]], [obj.right, obj.sub[2]]
    elif kind == "local":
        # Object i gets a share 0.54^i of the Gaussians and half the size of the first; the others sit apart from
        # it along the axes of a random frame.
        shares = torch.tensor([0.54**i for i in range(objects)])
        counts = (shares / shares.sum() * n).long().tolist()
        axes = quat_to_matrix(_random_quat(gen))
        scenes: list[GaussianScene] = []
        for i, count in enumerate(counts):
            design = _Design.random(gen, count, parts if i == 0 else max(parts // 2, 3), k)
            obj = design.whole(samples, capture)
            where = torch.zeros(3) if i == 0 else 2.2 * axes[:, (i - 1) % 3] * (1.0 if i <= 3 else -1.0)
            pose = Pose(tuple(_random_quat(gen).tolist()), tuple(where.tolist()), 1.0 if i == 0 else 0.5)
            base = sum(len(sc) for sc in scenes)
            scenes.append(apply_pose(obj.scene, pose))
            planes.append(pose.apply_plane(x_plane))
            lefts.append(obj.left + base)
            rights.append(obj.right + base)
        scene = GaussianScene.cat(scenes)
    elif kind == "asymmetric":
        blobs = _asymmetric_parts(gen, parts, k)
        scene = _sample_parts(blobs, _allocate(blobs, n), samples, k)
    else:
        raise ValueError(f"kind must be global, local, nested or asymmetric, got {kind!r}")

    if noise > 0:
        scene = scene.with_(means=scene.means + noise * torch.randn(len(scene), 3, generator=samples))
    n_object = len(scene)
    if clutter > 0:
        extra = _clutter(samples, int(round(clutter * n_object)), scene.means, scene.scales, k, CLUTTER_PAD)
        scene = GaussianScene.cat([scene, extra])
    if surroundings > 0:
        count = int(round(surroundings * n_object))
        extra = surroundings_of(scene.means[:n_object], scene.scales[:n_object], count, samples, k)
        scene = GaussianScene.cat([scene, extra])
    # Shuffle so that no method can lean on the order the halves were built in.
    perm = torch.randperm(len(scene), generator=samples)
    inverse = torch.empty_like(perm)
    inverse[perm] = torch.arange(len(perm))
    scene = scene.select(perm)
    lefts = [inverse[i] for i in lefts]
    rights = [inverse[i] for i in rights]
    clutter_idx = inverse[n_object:]
    if pose is not None:
        scene = apply_pose(scene, pose)
        planes = [pose.apply_plane(p) for p in planes]
    return SyntheticScene(scene, planes, lefts, rights, clutter_idx)
