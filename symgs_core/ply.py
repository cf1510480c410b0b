"""Gaussian scenes in the graphdeco PLY layout: read by property name, validate, repair what is safe, write.

graphdeco order: ``x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3``, all float32, with
``f_rest`` channel-major: ``f_rest_{c*K + k-1}`` is SH coefficient k (1..K) of colour channel c.

Reading accepts any property order, extra properties (ignored, reported) and float64 values. The header is
checked against the file size before the body is read, so a header that claims more Gaussians than the file
holds is refused without allocating for them. Repairs, counted in the report:
  * ``+inf`` / ``-inf`` opacity logits are clamped to logit(1 - 1/512) / logit(1/512);
  * zero quaternions (norm below 1e-12) become the identity (1, 0, 0, 0).
Unnormalised quaternions are normal in graphdeco files and are kept as stored. NaN anywhere, or an infinity in
any other property, is an error.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from .ply_header import DC, GEOMETRY, NORMALS, ROTATIONS, SCALES, PlyError, read_header
from .scene import SH_REST_COUNT, GaussianScene

# logit(1 - 1/512) and logit(1/512): the opacity range of an 8-bit alpha that avoids 0 and 1.
OPACITY_LOGIT_MAX = float(np.float32(math.log(511.0)))
OPACITY_LOGIT_MIN = -OPACITY_LOGIT_MAX

@dataclass
class PlyReport:
    """What reading a scene found.

    count       Gaussians read
    sh_degree   0..3, from the number of f_rest properties
    format      the PLY encoding (ascii, binary_little_endian, binary_big_endian)
    properties  vertex property names in file order
    ignored     properties present but not used (normals, colours, ...)
    repairs     repair name -> number of Gaussians repaired; empty when nothing was changed
    comments    header comments
    """

    count: int
    sh_degree: int
    format: str
    properties: list[str]
    ignored: list[str]
    repairs: dict[str, int] = field(default_factory=dict)
    comments: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def _to_scene(data: np.ndarray, rest: list[str], path: Path) -> tuple[GaussianScene, dict[str, int]]:
    """Scene from the structured vertex array, after the finiteness checks and repairs."""
    order = [*GEOMETRY, *DC, *rest, "opacity", *SCALES, *ROTATIONS]
    n = len(data)
    # One native-order float32 matrix [N, P]; float32 input keeps its exact bits.
    values = np.empty((n, len(order)), dtype=np.float32)
    for i, name in enumerate(order):
        values[:, i] = data[name]
    o = order.index("opacity")
    bad = ~np.isfinite(values)
    bad[:, o] = np.isnan(values[:, o])  # infinite opacities are repaired below
    if bad.any():
        counts = bad.sum(axis=0)
        where = ", ".join(f"{name} ({c} values)" for name, c in zip(order, counts, strict=True) if c)
        raise PlyError("non_finite", f"{path.name}: NaN or infinite values in {where}")

    repairs: dict[str, int] = {}
    opacity = values[:, o]
    for repair, infinity, limit in (
        ("opacity_pos_inf_clamped", np.inf, OPACITY_LOGIT_MAX),
        ("opacity_neg_inf_clamped", -np.inf, OPACITY_LOGIT_MIN),
    ):
        hit = opacity == infinity
        if hit.any():
            opacity[hit] = limit
            repairs[repair] = int(hit.sum())
    quats = values[:, -4:]
    zero = np.linalg.norm(quats.astype(np.float64), axis=1) < 1e-12
    if zero.any():
        quats[zero] = (1.0, 0.0, 0.0, 0.0)
        repairs["zero_quaternion_set_to_identity"] = int(zero.sum())

    k = len(rest) // 3
    r = 6 + 3 * k
    tensor = lambda a: torch.from_numpy(np.ascontiguousarray(a))
    scene = GaussianScene(
        means=tensor(values[:, 0:3]),
        quats=tensor(quats),
        scales=tensor(values[:, r + 1 : r + 4]),
        opacities=tensor(opacity),
        sh_dc=tensor(values[:, 3:6]),
        sh_rest=tensor(values[:, 6:r].reshape(n, 3, k).transpose(0, 2, 1)),  # channel-major -> [N, K, 3]
    )
    return scene, repairs


def read_scene(path: str | os.PathLike[str], *, max_gaussians: int | None = None) -> tuple[GaussianScene, PlyReport]:
    """Read a Gaussian scene and a report of what was found and repaired; raises PlyError on bad input."""
    from plyfile import PlyData, PlyParseError

    path = Path(path)
    header = read_header(path, max_gaussians=max_gaussians)
    names, rest = header.properties, list(header.rest)

    try:
        data = PlyData.read(str(path))["vertex"].data
    except (PlyParseError, ValueError, EOFError) as exc:
        code = "truncated" if "early end" in str(exc).lower() or isinstance(exc, EOFError) else "malformed"
        raise PlyError(code, f"{path.name}: cannot read the vertex data ({exc})") from None

    scene, repairs = _to_scene(data, rest, path)
    report = PlyReport(
        count=len(scene),
        sh_degree=scene.sh_degree,
        format=header.format,
        properties=names,
        ignored=[n for n in names if n not in header.used],
        repairs=repairs,
        comments=list(header.comments),
    )
    return scene, report


def load_scene(path: str | os.PathLike[str]) -> GaussianScene:
    """Read a Gaussian scene (see ``read_scene`` for what is accepted and repaired)."""
    return read_scene(path)[0]


def graphdeco_properties(sh_degree: int) -> list[str]:
    """Property names of the graphdeco layout for ``sh_degree``, in file order."""
    k = SH_REST_COUNT[sh_degree]
    rest = [f"f_rest_{i}" for i in range(3 * k)]
    return [*GEOMETRY, *NORMALS, *DC, *rest, "opacity", *SCALES, *ROTATIONS]


def ply_bytes(scene: GaussianScene, *, comments: tuple[str, ...] = ()) -> bytes:
    """The binary little-endian graphdeco PLY of ``scene`` (float32, zero normals).

    Built as one float32 matrix: a million Gaussians take a fraction of a second, where a structured array per
    property takes seconds.
    """
    n, k = len(scene), scene.sh_rest.shape[1]
    t = {name: v.detach().to("cpu", torch.float32) for name, v in scene.tensors().items()}
    flat = torch.cat(
        [t["means"], torch.zeros(n, 3), t["sh_dc"], t["sh_rest"].transpose(1, 2).reshape(n, 3 * k),
         t["opacities"][:, None], t["scales"], t["quats"]],
        dim=1,
    )  # fmt: skip
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments), f"element vertex {n}"]
    header += [f"property float {name}" for name in graphdeco_properties(scene.sh_degree)] + ["end_header"]
    return ("\n".join(header) + "\n").encode("ascii") + flat.numpy().astype("<f4", copy=False).tobytes()


def save_scene(scene: GaussianScene, path: str | os.PathLike[str], *, comments: tuple[str, ...] = ()) -> None:
    """Write ``scene`` to ``path`` as ``ply_bytes`` does."""
    Path(path).write_bytes(ply_bytes(scene, comments=comments))
