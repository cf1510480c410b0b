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

from .ply_header import DC, GEOMETRY, NORMALS, ROTATIONS, SCALES, TYPES, PlyError, PlyHeader, read_header
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


def _vertex_rows(path: Path, header: PlyHeader) -> np.ndarray | None:
    """The vertex rows mapped from the file as a structured array (no copy), for binary files whose elements have no
    lists (every row at a fixed size, the file's length already checked by the header); None otherwise."""
    if header.format == "ascii" or any(e.has_lists for e in header.elements):
        return None
    order = "<" if header.format == "binary_little_endian" else ">"
    offset = header.size
    for element in header.elements:
        dtype = np.dtype([(name, f"{order}{TYPES[kind][1]}{TYPES[kind][0]}") for name, kind, _ in element.properties])
        if element is header.vertex:
            if element.count == 0:
                return np.empty(0, dtype)
            return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=(element.count,))
        offset += element.count * dtype.itemsize
    raise AssertionError("the header has a vertex element")


def _float_matrix(rows: np.ndarray) -> np.ndarray | None:
    """The rows as a float32 matrix [N, P] (a view) when every property is a float32; None otherwise."""
    kinds = {rows.dtype.fields[name][0] for name in rows.dtype.names or ()}  # type: ignore[index]
    kind = kinds.pop() if len(kinds) == 1 else None
    if kind is None or kind.kind != "f" or kind.itemsize != 4:
        return None
    return np.ndarray((len(rows), len(rows.dtype.names)), kind, rows, 0, (rows.dtype.itemsize, 4))  # type: ignore[arg-type]


def _fill(out: np.ndarray, rows: np.ndarray, matrix: np.ndarray | None, names: list[str]) -> None:
    """Copy the named properties into the columns of ``out`` [N, len(names)] (a view of the attribute's array)."""
    if not names:
        return
    if matrix is None:
        for j, name in enumerate(names):
            out[:, j] = rows[name]
        return
    index = [rows.dtype.names.index(name) for name in names]  # type: ignore[union-attr]
    if index == list(range(index[0], index[0] + len(index))):
        out[...] = matrix[:, index[0] : index[0] + len(index)]  # one strided block copy: the usual layouts
    else:
        out[...] = matrix[:, index]


def _to_scene(rows: np.ndarray, rest: list[str], path: Path) -> tuple[GaussianScene, dict[str, int]]:
    """Scene from the structured vertex rows, after the finiteness checks and repairs: each attribute is copied once,
    straight into the native float32 array its tensor wraps (float32 input keeps its exact bits)."""
    n, k = len(rows), len(rest) // 3
    groups = {
        "means": list(GEOMETRY), "sh_dc": list(DC), "opacities": ["opacity"], "scales": list(SCALES),
        "quats": list(ROTATIONS),
    }  # fmt: skip
    matrix = _float_matrix(rows)
    values = {name: np.empty((n, len(names)), np.float32) for name, names in groups.items()}
    for name, names in groups.items():
        _fill(values[name], rows, matrix, names)
    sh_rest = np.empty((n, k, 3), np.float32)
    for c in range(3):  # f_rest is channel-major: f_rest_{c*K + j} is coefficient j+1 of channel c
        _fill(sh_rest[:, :, c], rows, matrix, rest[c * k : (c + 1) * k])
    values["sh_rest"] = sh_rest.reshape(n, 3 * k)
    groups["sh_rest"] = [rest[c * k + j] for j in range(k) for c in range(3)]

    # min and max carry NaN and the infinities through without a temporary array: the counts only when they hit.
    suspect = [name for name, v in values.items() if v.size and not np.isfinite([v.min(), v.max()]).all()]
    counts: dict[str, int] = {}
    for name in suspect:  # infinite opacities are repaired below
        invalid = np.isnan(values[name]) if name == "opacities" else ~np.isfinite(values[name])
        counts.update(zip(groups[name], invalid.sum(axis=0).tolist(), strict=True))
    if any(counts.values()):
        order = [*GEOMETRY, *DC, *rest, "opacity", *SCALES, *ROTATIONS]
        where = ", ".join(f"{prop} ({counts[prop]} values)" for prop in order if counts.get(prop))
        raise PlyError("non_finite", f"{path.name}: NaN or infinite values in {where}")

    repairs: dict[str, int] = {}
    opacity = values["opacities"].reshape(n)
    for repair, infinity, limit in (
        ("opacity_pos_inf_clamped", np.inf, OPACITY_LOGIT_MAX),
        ("opacity_neg_inf_clamped", -np.inf, OPACITY_LOGIT_MIN),
    ):
        hit = opacity == infinity
        if hit.any():
            opacity[hit] = limit
            repairs[repair] = int(hit.sum())
    quats = values["quats"]
    # Only rows whose every component is below 1e-12 can have a norm below it: the exact test runs on those alone.
    small = np.flatnonzero((np.abs(quats) < 1e-12).all(axis=1))
    zero = small[np.linalg.norm(quats[small].astype(np.float64), axis=1) < 1e-12]
    if len(zero):
        quats[zero] = (1.0, 0.0, 0.0, 0.0)
        repairs["zero_quaternion_set_to_identity"] = len(zero)

    values["opacities"] = opacity
    values["sh_rest"] = values["sh_rest"].reshape(n, k, 3)
    scene = GaussianScene(**{name: torch.from_numpy(v) for name, v in values.items()})
    return scene, repairs


def read_scene(path: str | os.PathLike[str], *, max_gaussians: int | None = None) -> tuple[GaussianScene, PlyReport]:
    """Read a Gaussian scene and a report of what was found and repaired; raises PlyError on bad input.

    Binary files without lists (the usual case, either byte order) are mapped and each attribute copied once from
    the mapping; ascii files and files with list properties are parsed by plyfile."""
    path = Path(path)
    header = read_header(path, max_gaussians=max_gaussians)
    names, rest = header.properties, list(header.rest)

    rows = _vertex_rows(path, header)
    if rows is None:
        from plyfile import PlyData, PlyParseError

        try:
            rows = PlyData.read(str(path))["vertex"].data
        except (PlyParseError, ValueError, EOFError) as exc:
            code = "truncated" if "early end" in str(exc).lower() or isinstance(exc, EOFError) else "malformed"
            raise PlyError(code, f"{path.name}: cannot read the vertex data ({exc})") from None

    scene, repairs = _to_scene(rows, rest, path)
    del rows  # unmaps the file
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
