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

from .scene import SH_REST_COUNT, GaussianScene

# logit(1 - 1/512) and logit(1/512): the opacity range of an 8-bit alpha that avoids 0 and 1.
OPACITY_LOGIT_MAX = float(np.float32(math.log(511.0)))
OPACITY_LOGIT_MIN = -OPACITY_LOGIT_MAX

_MAX_HEADER_BYTES = 1 << 20
_GEOMETRY = ("x", "y", "z")
_NORMALS = ("nx", "ny", "nz")
_DC = ("f_dc_0", "f_dc_1", "f_dc_2")
_SCALES = ("scale_0", "scale_1", "scale_2")
_ROTS = ("rot_0", "rot_1", "rot_2", "rot_3")
REQUIRED = _GEOMETRY + _DC + ("opacity",) + _SCALES + _ROTS

# PLY scalar types: byte size and numpy kind.
_TYPES = {
    "char": (1, "i"), "int8": (1, "i"), "uchar": (1, "u"), "uint8": (1, "u"),
    "short": (2, "i"), "int16": (2, "i"), "ushort": (2, "u"), "uint16": (2, "u"),
    "int": (4, "i"), "int32": (4, "i"), "uint": (4, "u"), "uint32": (4, "u"),
    "float": (4, "f"), "float32": (4, "f"), "double": (8, "f"), "float64": (8, "f"),
}  # fmt: skip
_FORMATS = {"ascii", "binary_little_endian", "binary_big_endian"}


class PlyError(ValueError):
    """A PLY file that cannot be read as a Gaussian scene; ``code`` says why in a machine-readable word.

    Codes: not_ply, unsupported_format, malformed, missing_property, bad_sh_count, truncated, non_finite,
    too_many_gaussians.
    """

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


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


@dataclass
class _Element:
    name: str
    count: int
    properties: list[tuple[str, str, str | None]]  # (name, value type, list length type or None)

    def min_row_bytes(self, ascii: bool) -> int:
        """The fewest bytes a row can take: exact for binary rows without lists (a list may be empty)."""
        if ascii:
            return 2 * len(self.properties)  # every value takes at least one character and one separator
        return sum(_TYPES[length or value][0] for _, value, length in self.properties)


@dataclass
class _Header:
    format: str
    elements: list[_Element]
    comments: list[str]
    size: int  # bytes up to and including the end_header line


def _parse_header(head: bytes, path: Path) -> _Header:
    if not head.startswith(b"ply\n") and not head.startswith(b"ply\r\n"):
        raise PlyError("not_ply", f"{path.name}: not a PLY file (it does not start with 'ply')")
    end = head.find(b"end_header")
    if end < 0:
        raise PlyError("not_ply", f"{path.name}: no 'end_header' in the first {_MAX_HEADER_BYTES} bytes")
    newline = head.find(b"\n", end)
    if newline < 0:
        raise PlyError("truncated", f"{path.name}: the file ends inside its header")
    try:
        lines = head[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError as exc:
        raise PlyError("malformed", f"{path.name}: header is not ASCII text ({exc})") from None

    fmt = None
    elements: list[_Element] = []
    comments: list[str] = []
    for number, raw in enumerate(lines, start=2):
        words = raw.split()
        if not words:
            continue
        keyword = words[0]
        bad = PlyError("malformed", f"{path.name}: header line {number} is malformed: {raw.strip()!r}")
        if keyword == "comment":
            comments.append(raw.strip()[len("comment") :].strip())
        elif keyword == "obj_info":
            continue
        elif keyword == "format":
            if len(words) != 3:
                raise bad
            fmt = words[1]
            if fmt not in _FORMATS:
                raise PlyError("unsupported_format", f"{path.name}: unknown PLY format {fmt!r}")
        elif keyword == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise bad
            elements.append(_Element(words[1], int(words[2]), []))
        elif keyword == "property":
            if not elements:
                raise bad
            if len(words) == 3 and words[1] in _TYPES:
                prop = (words[2], words[1], None)
            elif len(words) == 5 and words[1] == "list" and words[2] in _TYPES and words[3] in _TYPES:
                prop = (words[4], words[3], words[2])
            else:
                raise bad
            if any(p[0] == prop[0] for p in elements[-1].properties):
                raise PlyError("malformed", f"{path.name}: property {prop[0]!r} appears twice")
            elements[-1].properties.append(prop)
        else:
            raise bad
    if fmt is None:
        raise PlyError("malformed", f"{path.name}: header has no 'format' line")
    return _Header(fmt, elements, comments, newline + 1)


def _check_size(header: _Header, vertex: _Element, file_size: int, path: Path) -> None:
    """Refuse headers that claim more rows than the file can hold, before plyfile allocates for them."""
    body = file_size - header.size
    ascii = header.format == "ascii"
    needed = sum(e.count * e.min_row_bytes(ascii) for e in header.elements)
    if needed > body:
        others = "" if header.elements == [vertex] else " and its other elements"
        raise PlyError(
            "truncated",
            f"{path.name}: header claims {vertex.count} vertices{others}, at least {needed} bytes of data, "
            f"but the file holds only {body} bytes after the header",
        )


def _rest_names(names: list[str], path: Path) -> list[str]:
    rest = [n for n in names if n.startswith("f_rest_")]
    expected = {f"f_rest_{i}" for i in range(len(rest))}
    if set(rest) != expected:
        raise PlyError(
            "bad_sh_count",
            f"{path.name}: f_rest properties are not numbered 0..{len(rest) - 1} without gaps: {sorted(rest)[:8]}",
        )
    if len(rest) % 3 != 0 or len(rest) // 3 not in SH_REST_COUNT.values():
        raise PlyError(
            "bad_sh_count",
            f"{path.name}: {len(rest)} f_rest properties match no SH degree (expected 0, 9, 24 or 45 for degrees 0..3)",
        )
    return [f"f_rest_{i}" for i in range(len(rest))]


def _to_scene(data: np.ndarray, rest: list[str], path: Path) -> tuple[GaussianScene, dict[str, int]]:
    """Scene from the structured vertex array, after the finiteness checks and repairs."""
    order = [*_GEOMETRY, *_DC, *rest, "opacity", *_SCALES, *_ROTS]
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
    with open(path, "rb") as f:
        head = f.read(_MAX_HEADER_BYTES)
    header = _parse_header(head, path)
    vertex = next((e for e in header.elements if e.name == "vertex"), None)
    if vertex is None:
        raise PlyError("missing_property", f"{path.name}: no 'vertex' element")
    names = [p[0] for p in vertex.properties]
    missing = [n for n in REQUIRED if n not in names]
    if missing:
        raise PlyError("missing_property", f"{path.name}: missing required properties {', '.join(missing)}")
    rest = _rest_names(names, path)
    used = set(REQUIRED) | set(rest)
    for name, value_type, length in vertex.properties:
        if name in used and (length is not None or _TYPES[value_type][1] != "f"):
            kind = "a list" if length is not None else value_type
            raise PlyError("unsupported_format", f"{path.name}: property {name!r} is {kind}, expected float")
    if max_gaussians is not None and vertex.count > max_gaussians:
        raise PlyError(
            "too_many_gaussians", f"{path.name}: {vertex.count} Gaussians exceed the limit of {max_gaussians}"
        )
    _check_size(header, vertex, path.stat().st_size, path)

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
        ignored=[n for n in names if n not in used],
        repairs=repairs,
        comments=header.comments,
    )
    return scene, report


def load_scene(path: str | os.PathLike[str]) -> GaussianScene:
    """Read a Gaussian scene (see ``read_scene`` for what is accepted and repaired)."""
    return read_scene(path)[0]


def graphdeco_properties(sh_degree: int) -> list[str]:
    """Property names of the graphdeco layout for ``sh_degree``, in file order."""
    k = SH_REST_COUNT[sh_degree]
    rest = [f"f_rest_{i}" for i in range(3 * k)]
    return [*_GEOMETRY, *_NORMALS, *_DC, *rest, "opacity", *_SCALES, *_ROTS]


def save_scene(scene: GaussianScene, path: str | os.PathLike[str], *, comments: tuple[str, ...] = ()) -> None:
    """Write ``scene`` as a binary little-endian graphdeco PLY (float32, zero normals)."""
    from plyfile import PlyData, PlyElement

    n, k = len(scene), scene.sh_rest.shape[1]
    t = {name: v.detach().to("cpu", torch.float32).numpy() for name, v in scene.tensors().items()}
    columns = [
        t["means"],
        np.zeros((n, 3), dtype=np.float32),
        t["sh_dc"],
        t["sh_rest"].transpose(0, 2, 1).reshape(n, 3 * k),  # [N, K, 3] -> channel-major
        t["opacities"][:, None],
        t["scales"],
        t["quats"],
    ]
    flat = np.concatenate(columns, axis=1)
    names = graphdeco_properties(scene.sh_degree)
    rows = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        rows[name] = flat[:, i]
    element = PlyElement.describe(rows, "vertex")
    PlyData([element], text=False, byte_order="<", comments=list(comments)).write(str(path))
